"""The optimisation loop shared by the world model's small heads (proprioception, frame success):
AdamW with a cosine schedule, one minibatch loss per step, a 50-point loss history."""
from __future__ import annotations

import time
from typing import Callable

import torch
import torch.nn as nn


def fit_head(head: nn.Module, batch_loss: Callable[[torch.Generator], torch.Tensor], *, steps: int, lr: float,
             seed: int, weight_decay: float = 1e-4, progress=None) -> dict:
    """Minimise ``batch_loss(gen)`` (a fresh minibatch per call, drawn with ``gen``) for ``steps`` steps.

    Returns the loss history, its last value and the wall seconds; leaves ``head`` in eval mode.
    """
    opt = torch.optim.AdamW(head.parameters(), lr=lr, weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    gen = torch.Generator().manual_seed(seed)
    hist, t0 = [], time.perf_counter()
    head.train()
    for step in range(steps):
        loss = batch_loss(gen)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if step % max(1, steps // 50) == 0 or step == steps - 1:
            hist.append(float(loss.detach()))
        if progress is not None:
            progress.update(1)
    head.eval()
    return {"history": hist, "final": hist[-1] if hist else None, "seconds": time.perf_counter() - t0}
