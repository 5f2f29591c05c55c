"""A guard against exploiting the world model (beyond the paper): an ensemble of done classifiers.

``guard_heads`` small classifiers read the action world model's hidden state of a frame (as the
``embedding`` reward head does) and predict the simulator's success flag. Each is fitted on its own
bootstrap resample of frames from IND training episodes, collect's failures included, with the two
classes weighted equally. Where the policy has driven the world model somewhere the data never
went, the heads disagree. With ``rl.guard`` on, the world-model environment
  - subtracts ``guard_coef * max_step_reward * std`` of the ensemble's probabilities every step, and
  - counts a done-head termination as a success (and pays ``success_return``) only if the
    ensemble's mean probability also reaches ``theta_done``; otherwise the episode goes on.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


class DoneEnsemble(nn.Module):
    def __init__(self, dim: int, heads: int, hidden: int = 64):
        super().__init__()
        self.heads = nn.ModuleList(
            nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, 1)) for _ in range(heads))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return torch.stack([head(h)[:, 0] for head in self.heads])  # (B, D) -> (K, B) logits

    @torch.no_grad()
    def probs(self, h: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self(h.float()))  # (K, B)


def fit_done_ensemble(hidden: torch.Tensor, success: torch.Tensor, *, heads: int, steps: int, lr: float,
                      seed: int, device: str = "cpu") -> tuple[DoneEnsemble, list[float]]:
    """Fit each head on its own bootstrap resample (class-balanced BCE). hidden (M, D), success (M,).

    Trained on ``device``, where the returned ensemble stays; the resamples are drawn on the CPU.
    """
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    model = DoneEnsemble(hidden.shape[1], heads).to(device)
    hidden = hidden.to(device)
    y = success.float().cpu()
    pos, neg = torch.nonzero(y > 0.5)[:, 0], torch.nonzero(y <= 0.5)[:, 0]
    if len(pos) == 0 or len(neg) == 0:
        raise ValueError(f"the done ensemble needs frames of both classes: {len(pos)} successful, {len(neg)} not")
    boots = [(pos[torch.randint(len(pos), (len(pos),), generator=gen)],
              neg[torch.randint(len(neg), (len(neg),), generator=gen)]) for _ in range(heads)]
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    losses = []
    model.train()
    for _ in range(steps):
        loss = 0.0
        for k, (bp, bn) in enumerate(boots):  # half of each batch from either class
            idx = torch.cat([bp[torch.randint(len(bp), (64,), generator=gen)], bn[torch.randint(len(bn), (64,), generator=gen)]])
            loss = loss + F.binary_cross_entropy_with_logits(model.heads[k](hidden[idx].float())[:, 0], y[idx].to(device))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()) / heads)
    model.eval()
    return model, losses


class Guard:
    """What the world-model env applies each step: a penalty and a veto on unconfirmed successes."""

    def __init__(self, ensemble: DoneEnsemble, coef: float, theta: float):
        self.ensemble, self.coef, self.theta = ensemble, coef, theta

    def __call__(self, hidden: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """(std (B,) of the heads' probabilities, confirmed (B,) bool: their mean reaches theta)."""
        p = self.ensemble.probs(hidden.to(next(self.ensemble.parameters()).device))  # (K, B)
        return p.std(0).cpu().numpy().astype(np.float64), (p.mean(0) >= self.theta).cpu().numpy()
