"""The interface every world-model reward module implements (``rule`` is the simulator's own)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class StepBatch:
    """What a world-model step (or a real frame, in diagnostics) offers a reward module."""

    tokens: torch.Tensor  # (B, h, w) long
    done_prob: torch.Tensor  # (B,) action-WM done head
    hidden: torch.Tensor  # (B, D) action-WM pooled features of the frame
    goal_index: np.ndarray  # (B,) row of each env's goal in the goals artifact
    third: torch.Tensor | None = None  # (B, 3, H, W) in [0, 1], decoded; set when a module needs frames
    wrist: torch.Tensor | None = None


class RewardModule:
    """``reset(rows, batch)`` at episode starts, then ``__call__(batch) -> (B,)`` rewards per step."""

    name = "base"
    needs_frames = False

    def reset(self, rows: np.ndarray, batch: StepBatch) -> None:
        """Episodes restarted in ``rows``; ``batch`` holds their initial frames (all B rows)."""

    def __call__(self, batch: StepBatch) -> np.ndarray:
        raise NotImplementedError
