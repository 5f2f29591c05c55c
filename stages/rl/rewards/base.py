"""The interface every reward module implements, and the success payout every environment applies."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch

from stages.common.returns import success_return  # noqa: F401  (re-exported: every env applies it)


@dataclass
class StepBatch:
    """What a world-model step (or a real frame, in diagnostics) offers a reward module."""

    tokens: torch.Tensor  # (B, h, w) long
    done_prob: torch.Tensor  # (B,) action-WM done head
    hidden: torch.Tensor  # (B, D) action-WM pooled features of the frame
    goal_index: np.ndarray  # (B,) row of each env's goal in the goals artifact
    third: torch.Tensor | None = None  # (B, 3, H, W) in [0, 1], decoded; set when a module needs frames
    wrist: torch.Tensor | None = None
    rule_reward: np.ndarray | None = None  # (B,) the simulator's normalised dense reward, where known


@dataclass
class RewardParts:
    """What modules are built from: the goal-distance function and the fitted heads (by name)."""

    distance: object | None = None  # stages.rl.rewards.wm.GoalDistance
    heads: dict = field(default_factory=dict)  # name -> fitted head (stages.rl.rewards.heads)


class RewardModule:
    """``reset(rows, batch)`` at episode starts, then ``__call__(batch) -> (B,)`` rewards per step.

    ``max_step_reward`` bounds one step's reward from above: a success that ends an episode is an
    absorbing state paid that bound on its own step and every step left until truncation
    (``success_return``), so no policy earns more by lingering next to the goal than by reaching it.
    ``env`` says where PPO runs with the module:
    ``wm`` (the world model scores its own frames) or ``sim`` (the simulator's reward).
    """

    name: ClassVar[str] = "base"
    env: ClassVar[str] = "wm"
    needs_frames: ClassVar[bool] = False
    needs_head: ClassVar[str | None] = None  # the fitted head it reads (stages.rl.rewards.fit)
    stateless: ClassVar[bool] = True  # a step's reward depends on that step's frame only
    max_step_reward: float = 1.0

    @classmethod
    def build(cls, parts: RewardParts, cfg, num_envs: int) -> "RewardModule":
        """The module as the rl config ``cfg`` sets it up, for ``num_envs`` environments."""
        raise NotImplementedError

    def reset(self, rows: np.ndarray, batch: StepBatch) -> None:
        """Episodes restarted in ``rows``; ``batch`` holds their initial frames, one per row of ``rows`` in
        that order (the env decodes only the restarted envs' frames)."""

    def __call__(self, batch: StepBatch) -> np.ndarray:
        raise NotImplementedError

    def along(self, first: StepBatch, frames: StepBatch) -> np.ndarray:
        """Rewards (T,) along one episode: ``first`` its initial frame (B = 1), ``frames`` frames 1..T (B = T)."""
        if self.stateless:
            return np.asarray(self(frames), dtype=np.float64)
        raise NotImplementedError(f"reward module {self.name!r} keeps state across steps and must define along()")
