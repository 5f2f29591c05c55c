"""Mixed precision: bf16 autocast where the hardware runs bf16 matmuls fast, fp32 elsewhere.

CPUs differ: on one 2-core machine without native bf16 a bf16 matmul ran at ~1 GFLOP/s (fp32 ~85);
on a 2-core Xeon with AMX, a bf16 linear layer ran 4x and a bare matmul ~6x faster than fp32
(benchmarks/wm_precision.py).
So ``auto`` decides by measuring: bf16 on CUDA always, on a CPU only if a bf16 matmul is at least
``FAST_RATIO`` times faster than fp32 there (measured once per process; 38 ms on that Xeon).

```python
from stages.common.precision import autocast
with autocast(device, "auto"):   # "fp32" | "bf16" | "auto"
    out = model(x)
```

Results then depend on the machine (as they already do between CPU and CUDA); the device and this
decision are not part of an artifact's key. The rl stage records what ``auto`` chose in its
``metrics.json`` (``ppo/wm_dtype``).
"""
from __future__ import annotations

import contextlib
import functools
import time
from typing import Literal

import torch

Precision = Literal["fp32", "bf16", "auto"]
FAST_RATIO = 1.5  # bf16 must beat fp32 by this factor on the CPU for ``auto`` to choose it


@functools.lru_cache(maxsize=1)
def cpu_bf16_speedup() -> float:
    """fp32 time / bf16 time of a (256, 256) x (256, 512) matmul on this CPU, best of 5 (one thread count as set)."""
    a, b = torch.randn(256, 256), torch.randn(256, 512)
    ab, bb = a.bfloat16(), b.bfloat16()

    def best(x, y) -> float:
        torch.matmul(x, y)
        times = []
        for _ in range(5):
            t = time.perf_counter()
            for _ in range(4):
                torch.matmul(x, y)
            times.append(time.perf_counter() - t)
        return min(times)

    return best(a, b) / best(ab, bb)


def resolved(device: str | torch.device, mode: Precision) -> str:
    """The precision ``mode`` means on ``device``: "fp32" or "bf16"."""
    if mode not in ("fp32", "bf16", "auto"):
        raise ValueError(f"precision must be 'fp32', 'bf16' or 'auto', got {mode!r}")
    if mode != "auto":
        return mode
    if torch.device(device).type == "cuda":
        return "bf16"
    return "bf16" if cpu_bf16_speedup() >= FAST_RATIO else "fp32"


def conv_layout(module: torch.nn.Module, device: str | torch.device, mode: Precision) -> torch.nn.Module:
    """``module`` in place in channels-last memory layout where its convolutions run in bf16 on a CPU.

    oneDNN's bf16 convolutions are faster channels-last (2-core Xeon with AMX, 1 thread: the
    tokenizer's decoder 33 -> 23 ms, LPIPS features 8.2 -> 4.9 ms for 16 frames); in fp32 it made no
    difference worth having, so fp32 and CUDA leave the module as it is. Values are unchanged up to
    rounding; returns ``module``.
    """
    if torch.device(device).type == "cpu" and resolved(device, mode) == "bf16":
        module.to(memory_format=torch.channels_last)
    return module


def autocast(device: str | torch.device, mode: Precision):
    """A context in which matmuls run in the resolved precision (a no-op for fp32)."""
    if resolved(device, mode) == "fp32":
        return contextlib.nullcontext()
    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)
