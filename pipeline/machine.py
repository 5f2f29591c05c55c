"""What computed an artifact: the CPU model, core count and library versions, recorded in every manifest.

A key names a computation (stage code, config, input keys), not its bytes: floating-point results
depend on the CPU's vector units and the kernels a library picks for them, so one key built on two
kinds of machine can hold different weights (docs/engine.md, "Keys name the computation, not the
bytes"). The manifest's ``machine`` says which kind built an artifact, so results measured on two
machines' artifacts of the same key are not mistaken for one policy.
"""
from __future__ import annotations

import os
import platform
import sys


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def describe() -> dict:
    """{"cpu", "cores", "platform", "python", and "torch" / "numpy" when the stage imported them}."""
    out = {"cpu": cpu_model(), "cores": os.cpu_count(), "platform": platform.platform(),
           "python": platform.python_version()}
    for lib in ("torch", "numpy"):  # only if already imported: a manifest never pays for an import
        mod = sys.modules.get(lib)
        if mod is not None:
            out[lib] = getattr(mod, "__version__", "unknown")
    return out
