"""Reward models fitted to the simulator's rule reward: the two learned-reward baselines.

``embedding`` (iVideoGPT-style): an MLP on the action world model's hidden state of a frame.
``proxy`` (DiWA-style): a separate small CNN on the (tokenizer-decoded) frame, both views stacked.
Both predict the rule reward (normalised dense, in [0, 1]) of the frame; their output is clipped to
that range, so a success that ends an episode can be paid the maximum for the steps left.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn

from stages.rl.rewards.base import RewardModule, RewardParts, StepBatch


def _device(module: nn.Module) -> torch.device:
    return next(module.parameters()).device


class EmbeddingHead(nn.Module):
    def __init__(self, dim: int, hidden: int = 128):
        super().__init__()
        self.net = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, 1))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.net(h)[:, 0]  # (B, D) -> (B,)


class ProxyCNN(nn.Module):
    def __init__(self, width: int = 32):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(6, width, 4, 2, 1), nn.GELU(),  # 64 -> 32
            nn.Conv2d(width, 2 * width, 4, 2, 1), nn.GELU(),  # -> 16
            nn.Conv2d(2 * width, 2 * width, 4, 2, 1), nn.GELU(),  # -> 8
            nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(2 * width, 1),
        )

    def forward(self, third: torch.Tensor, wrist: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([third, wrist], 1) * 2 - 1)[:, 0]  # (B, 3, H, W) x 2 -> (B,)


class EmbeddingReward(RewardModule):
    name = "embedding"
    needs_head = "embedding"

    def __init__(self, head: EmbeddingHead):
        self.head = head.eval()

    @classmethod
    def build(cls, parts: RewardParts, cfg, num_envs: int) -> "EmbeddingReward":
        return cls(parts.heads["embedding"])

    @torch.no_grad()
    def __call__(self, batch: StepBatch) -> np.ndarray:
        h = batch.hidden.float().to(_device(self.head))  # the env's batches are on its device, diagnostics' on the CPU
        return self.head(h).clamp(0.0, 1.0).cpu().numpy().astype(np.float64)


class ProxyReward(RewardModule):
    name = "proxy"
    needs_frames = True
    needs_head = "proxy"

    def __init__(self, cnn: ProxyCNN):
        self.cnn = cnn.eval()

    @classmethod
    def build(cls, parts: RewardParts, cfg, num_envs: int) -> "ProxyReward":
        return cls(parts.heads["proxy"])

    @torch.no_grad()
    def __call__(self, batch: StepBatch) -> np.ndarray:
        dev = _device(self.cnn)
        return self.cnn(batch.third.to(dev), batch.wrist.to(dev)).clamp(0.0, 1.0).cpu().numpy().astype(np.float64)
