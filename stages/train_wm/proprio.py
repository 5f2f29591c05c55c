"""The action world model's proprioception head: the robot's next state, so that the policy's
observation (``stages.sft.observation``) is complete inside the world model too.

    next_proprio = proprio + scale * MLP([proprio_t, action_t, Linear(codes_{t+1})])

``proprio`` is ``stages.common.proprio`` (TCP position, orientation, gripper opening); ``codes_{t+1}``
is the +-1 latent of the next frame (the one the world model just predicted), which tells the head
what the arm ran into (a closed gripper stops at the object's width, a pushed object resists).
The delta is normalised per dimension by its training std (``scale``). Trained by regression on
consecutive world-model steps of the training episodes with teacher-forced (real) next frames.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn

from stages.common.proprio import PROPRIO_DIM, tcp_position_m
from stages.train_wm.head_fit import fit_head

ACTION_DIM = 7
CHECKPOINT = "proprio_head.pt"


class ProprioHead(nn.Module):
    """(proprio (B, 10), action (B, 7), next codes (B, bits, h, w)) -> next proprio (B, 10)."""

    def __init__(self, bits: int, grid: tuple[int, int], hidden: int = 256, frame_dim: int = 128):
        super().__init__()
        self.bits, self.grid, self.hidden, self.frame_dim = bits, tuple(grid), hidden, frame_dim
        self.frame = nn.Sequential(nn.Flatten(), nn.Linear(bits * grid[0] * grid[1], frame_dim), nn.GELU())
        self.mlp = nn.Sequential(nn.Linear(PROPRIO_DIM + ACTION_DIM + frame_dim, hidden), nn.GELU(),
                                 nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, PROPRIO_DIM))
        self.register_buffer("delta_scale", torch.ones(PROPRIO_DIM))

    def forward(self, proprio: torch.Tensor, action: torch.Tensor, next_codes: torch.Tensor) -> torch.Tensor:
        z = self.mlp(torch.cat([proprio, action, self.frame(next_codes)], 1))  # (B, 10) normalised delta
        return proprio + self.delta_scale * z

    def config(self) -> dict:
        return {"bits": self.bits, "grid": list(self.grid), "hidden": self.hidden, "frame_dim": self.frame_dim}


def transitions(episodes, codes_fn) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(proprio_t (M, 10), action_t (M, 7), codes_{t+1} (M, bits, h, w), proprio_{t+1} (M, 10)) of every step."""
    p0, a, c1, p1 = [], [], [], []
    for e in episodes:
        p0.append(e.proprio[:-1]), a.append(e.actions), p1.append(e.proprio[1:])
        c1.append(codes_fn(e.tokens[1:]))
    cat = lambda xs: torch.from_numpy(np.concatenate(xs)).float()  # noqa: E731
    return cat(p0), cat(a), torch.cat(c1).float(), cat(p1)


def train_proprio_head(head: ProprioHead, data, *, steps: int, batch_size: int, lr: float, seed: int,
                       device: str = "cpu", progress=None) -> dict:
    """Fit the head by MSE on normalised deltas; returns the loss history and wall seconds."""
    p0, a, c1, p1 = (t.to(device) for t in data)
    delta = p1 - p0
    head.delta_scale.copy_(delta.std(0).clamp_min(1e-4))

    def batch_loss(gen: torch.Generator) -> torch.Tensor:
        idx = torch.randint(0, len(p0), (min(batch_size, len(p0)),), generator=gen).to(device)
        pred = head(p0[idx], a[idx], c1[idx])
        return (((pred - p1[idx]) / head.delta_scale) ** 2).mean()

    return fit_head(head, batch_loss, steps=steps, lr=lr, seed=seed, progress=progress)


@torch.no_grad()
def horizon_errors(head: ProprioHead, episodes, codes_fn, horizons: tuple[int, ...], starts: list[tuple[int, int]],
                   device: str = "cpu") -> dict:
    """TCP position error (cm) after h open-loop head steps from each start, next to copy-last.

    The head runs on its own predictions (open loop in proprioception) with the real next frames
    and actions of the episode (teacher-forced images). ``starts``: (episode index, start step) with
    at least max(horizons) steps left. Returns mean error and its normal 95% half-width per horizon.
    """
    h_max = max(horizons)
    errs = {h: [] for h in horizons}
    base = {h: [] for h in horizons}
    for i, s in starts:
        e = episodes[i]
        p = torch.from_numpy(e.proprio[s: s + 1]).float().to(device)
        codes = codes_fn(e.tokens[s + 1: s + h_max + 1]).float().to(device)
        acts = torch.from_numpy(e.actions[s: s + h_max]).float().to(device)
        for k in range(h_max):
            p = head(p, acts[k: k + 1], codes[k: k + 1])
            if k + 1 in errs:
                true = tcp_position_m(e.proprio[s + k + 1])
                errs[k + 1].append(100 * float(np.linalg.norm(tcp_position_m(p.cpu().numpy()[0]) - true)))
                base[k + 1].append(100 * float(np.linalg.norm(tcp_position_m(e.proprio[s]) - true)))
    out = {}
    for h in horizons:
        for name, v in (("head", errs[h]), ("copy_last", base[h])):
            v = np.asarray(v)
            out[f"h{h}/tcp_error_cm/{name}"] = float(v.mean()) if len(v) else None
            out[f"h{h}/tcp_error_cm/{name}_ci95"] = float(1.96 * v.std(ddof=1) / np.sqrt(len(v))) if len(v) > 1 else None
    out["starts"] = len(starts)
    return out


def save_head(head: ProprioHead, path) -> None:
    tmp = str(path) + ".tmp"
    torch.save({"config": head.config(), "state_dict": head.state_dict()}, tmp)
    import os

    os.replace(tmp, path)


def load_head(path, device: str = "cpu") -> ProprioHead:
    ck = torch.load(path, map_location=device, weights_only=True)
    cfg = ck["config"]
    head = ProprioHead(cfg["bits"], tuple(cfg["grid"]), cfg["hidden"], cfg["frame_dim"]).to(device)
    head.load_state_dict(ck["state_dict"])
    return head.eval()
