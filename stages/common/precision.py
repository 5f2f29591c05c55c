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
from typing import Callable, Literal

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


CHANNELS_LAST_GAIN = 1.1  # fp32 on a CPU: channels-last must be this much faster for ``conv_layout`` to keep it


def layout_of(module: torch.nn.Module) -> str:
    """"channels_last" or "default": the layout ``conv_layout`` left ``module`` in ("default" if never given to it)."""
    return getattr(module, "chosen_layout", "default")


def _best_seconds(call: Callable[[], object], repeats: int = 3, calls: int = 2) -> float:
    call()  # warm-up: oneDNN builds its kernels for the new layout here
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for _ in range(calls):
            call()
        best = min(best, time.perf_counter() - t)
    return best


@torch.no_grad()
def conv_layout(module: torch.nn.Module, device: str | torch.device, mode: Precision,
                probe: Callable[[], object] | None = None) -> torch.nn.Module:
    """``module`` in place in the memory layout its convolutions run faster in on this CPU; returns ``module``.

    bf16 on a CPU: channels-last, the layout oneDNN's bf16 convolutions are fast in (2-core Xeon with
    AMX, 1 thread: the tokenizer's decoder 33 -> 23 ms, LPIPS features 8.2 -> 4.9 ms for 16 frames).
    fp32 on a CPU: it depends on the CPU (that Xeon: channels-last 1.1 ms slower for the decoder; a
    2-core Xeon without AMX: the decoder 1.1-1.6x faster channels-last, the world-model env with
    LPIPS 1.10x, benchmarks/conv_layout.py), so with ``probe`` (a call that
    runs the module on a representative batch, in the caller's precision) both layouts are timed and
    channels-last is kept if it is at least ``CHANNELS_LAST_GAIN`` times faster; without a probe fp32
    keeps the default layout. CUDA: unchanged. Values are unchanged up to rounding. The decision is
    made once per module and precision (``layout_of`` reads it).
    """
    precision = resolved(device, mode)
    if torch.device(device).type != "cpu" or getattr(module, "chosen_for", None) == precision:
        return module
    if precision == "bf16":
        choice = "channels_last"
    elif probe is None:
        choice = "default"
    else:
        module.to(memory_format=torch.contiguous_format)
        default = _best_seconds(probe)
        module.to(memory_format=torch.channels_last)
        fast = _best_seconds(probe)
        choice = "channels_last" if default >= CHANNELS_LAST_GAIN * fast else "default"
    module.to(memory_format=torch.channels_last if choice == "channels_last" else torch.contiguous_format)
    module.chosen_layout, module.chosen_for = choice, precision
    return module


def autocast(device: str | torch.device, mode: Precision):
    """A context in which matmuls run in the resolved precision (a no-op for fp32)."""
    if resolved(device, mode) == "fp32":
        return contextlib.nullcontext()
    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)
