"""A frame-only success classifier: is the task done in THIS frame, whatever led to it?

    p(success | frame) = sigmoid(MLP(Conv(codes_t)))

``codes_t`` is the +-1 latent of one frame (both views, ``tokenize``'s grid). The world model's own
done head reads the MaskGIT head's features of the frame, which carry the backbone's temporal context
(the previous frames and actions): from demonstrations that always succeed it can learn "the arm has
executed the approach" instead of "the object is at the goal". This head sees one frame and nothing
else, so it can only answer from what the frame shows. Trained on the training episodes' frames with
their success labels (near-miss episodes' frames are negatives), positives and negatives weighted
half each.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from stages.train_wm.head_fit import fit_head

CHECKPOINT = "success_head.pt"


class SuccessHead(nn.Module):
    """(codes (B, bits, h, w)) -> success logit (B,)."""

    def __init__(self, bits: int, grid: tuple[int, int], width: int = 64, hidden: int = 128):
        super().__init__()
        self.bits, self.grid, self.width, self.hidden = bits, tuple(grid), width, hidden
        self.conv = nn.Sequential(nn.Conv2d(bits, width, 3, padding=1), nn.GELU(),
                                  nn.Conv2d(width, width, 3, padding=1), nn.GELU())
        self.mlp = nn.Sequential(nn.Flatten(), nn.Linear(width * grid[0] * grid[1], hidden), nn.GELU(),
                                 nn.Linear(hidden, 1))

    def forward(self, codes: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.conv(codes))[:, 0]  # (B, bits, h, w) -> (B,)

    def config(self) -> dict:
        return {"bits": self.bits, "grid": list(self.grid), "width": self.width, "hidden": self.hidden}


def labelled_frames(episodes, codes_fn) -> tuple[torch.Tensor, torch.Tensor]:
    """(codes (M, bits, h, w), success (M,)) of every frame of ``episodes``."""
    codes = torch.cat([codes_fn(e.tokens) for e in episodes]).float()
    labels = torch.from_numpy(np.concatenate([e.done for e in episodes])).float()
    return codes, labels


def train_success_head(head: SuccessHead, data, *, steps: int, batch_size: int, lr: float, seed: int,
                       device: str = "cpu") -> dict:
    """Class-balanced BCE (each batch half positives, half negatives); loss history and wall seconds."""
    codes, labels = (t.to(device) for t in data)
    pos, neg = torch.nonzero(labels > 0.5)[:, 0], torch.nonzero(labels <= 0.5)[:, 0]
    if not len(pos) or not len(neg):
        raise ValueError(f"success head needs both classes, got {len(pos)} success and {len(neg)} other frames")
    half = max(1, batch_size // 2)

    def batch_loss(gen: torch.Generator) -> torch.Tensor:
        idx = torch.cat([pos[torch.randint(0, len(pos), (half,), generator=gen)],
                         neg[torch.randint(0, len(neg), (half,), generator=gen)]])
        return F.binary_cross_entropy_with_logits(head(codes[idx]), labels[idx])

    return fit_head(head, batch_loss, steps=steps, lr=lr, seed=seed)


@torch.no_grad()
def success_prob(head: SuccessHead, codes: torch.Tensor, batch: int = 1024) -> torch.Tensor:
    """(M, bits, h, w) codes -> (M,) success probabilities."""
    return torch.cat([torch.sigmoid(head(codes[i: i + batch])) for i in range(0, len(codes), batch)])
