"""``wm``: the paper's reward, alpha * sparse + beta * dense, both from the world model; our dense term by default.

sparse = 1 when the action WM's done head >= theta_sps. dense, by ``dense``:
  - ``progress``: LPIPS(frame, episode's first frame) - LPIPS(frame, goal): how far the frame has
    come from the start and how close it is to the goal, in [-1, 1]. The distance to the goal alone is
    dominated by the arm; the distance to the start adds what the episode has changed (docs/rl.md,
    "The dense term").
  - ``similarity``: the paper's perceptual *similarity* to the environment's goal frame, 1 - LPIPS;
  - ``potential``: the shaping term gamma * Phi(s') - Phi(s) with Phi = -LPIPS to the goal (policy
    invariant; sums to a telescoping difference, so lingering earns nothing).
LPIPS is averaged over both views. The goal frames' LPIPS features are computed once, an episode's
first frame's at its start, the current frame's once per step. The authors' environment added LPIPS *distance* (paying
the agent to move away from the goal): tests/rl pin the sign.
"""
from __future__ import annotations

import copy

import numpy as np
import torch

from stages.common.precision import autocast, conv_layout, resolved
from stages.rl.rewards.base import RewardModule, RewardParts, StepBatch


PROBE_FRAMES = 32  # frames per view the LPIPS network's layout is timed on (an env step scores num_envs, 16 at small)


class GoalDistance:
    """LPIPS distance of frames to their goal frames, with the goals' features cached.

    ``dtype`` ("fp32" | "bf16" | "auto", stages.common.precision): the AlexNet convolutions' precision
    (features are normalised and compared in fp32). On a CPU a copy of the network runs in the layout
    ``conv_layout`` chose (channels-last for bf16; for fp32 where it timed faster).
    """

    def __init__(self, goal_third: torch.Tensor, goal_wrist: torch.Tensor, device: str = "cpu", dtype: str = "fp32"):
        from stages.common.lpips import get_lpips

        self.dtype = resolved(device, dtype)
        self.device = device
        net = get_lpips(device)
        if torch.device(device).type == "cpu":  # a copy in the layout it runs faster in here (timed on some goals)
            self.net = copy.deepcopy(net)
            probe = goal_third[:PROBE_FRAMES], goal_wrist[:PROBE_FRAMES]  # about an env step's batch, not every goal
            conv_layout(self.net, device, self.dtype, probe=lambda: self.features(*probe))
        else:
            self.net = net
        self.goal_feats = self.features(goal_third, goal_wrist)  # per view: [(G, C, h, w)] per layer

    @torch.no_grad()
    def features(self, *views: torch.Tensor) -> list[list[torch.Tensor]]:
        """LPIPS features of each view's frames (N, 3, H, W) in [0, 1]."""
        with autocast(self.device, self.dtype):
            return [self.net.features(v.to(self.device) * 2 - 1) for v in views]

    @torch.no_grad()
    def between(self, feats: list[list[torch.Tensor]], others: list[list[torch.Tensor]]) -> np.ndarray:
        """(B,) mean LPIPS over both views between two ``features`` outputs (rows paired)."""
        d = 0.0
        for f, o in zip(feats, others):
            d = d + self.net.distance_from_features(f, o)
        return (d / 2).cpu().numpy().astype(np.float64)

    def goals_of(self, goal_index: np.ndarray) -> list[list[torch.Tensor]]:
        idx = torch.as_tensor(goal_index, dtype=torch.long, device=self.device)
        return [[g[idx] for g in gf] for gf in self.goal_feats]

    @torch.no_grad()
    def __call__(self, third: torch.Tensor, wrist: torch.Tensor, goal_index: np.ndarray) -> np.ndarray:
        """(B,) mean LPIPS over both views of frames (B, 3, H, W) in [0, 1] to goals[goal_index]."""
        return self.between(self.features(third, wrist), self.goals_of(goal_index))


class WMReward(RewardModule):
    name = "wm"
    needs_frames = True
    stateless = False  # potential remembers the previous frame's potential, progress the first frame
    DENSE = ("progress", "similarity", "potential")

    def __init__(self, distance: GoalDistance, *, alpha: float, beta: float, theta_sps: float,
                 dense: str = "progress", gamma: float = 0.99, num_envs: int = 1):
        if dense not in self.DENSE:
            raise ValueError(f"dense must be one of {self.DENSE}, got {dense!r}")
        self.distance, self.alpha, self.beta, self.theta = distance, alpha, beta, theta_sps
        self.dense_kind, self.gamma = dense, gamma
        self.needs_frames = beta > 0  # sparse only (beta 0): the environment decodes no frame for it
        self.num_envs = num_envs
        self.prev_phi = np.zeros(num_envs)
        self.start_feats: list[list[torch.Tensor]] | None = None  # progress: per view, per layer (num_envs, C, h, w)
        # every dense step is <= 1 (LPIPS distance lies in [0, 1])
        self.max_step_reward = alpha + beta

    @classmethod
    def build(cls, parts: RewardParts, cfg, num_envs: int) -> "WMReward":
        return cls(parts.distance, alpha=cfg.alpha, beta=cfg.beta, theta_sps=cfg.theta_sps, dense=cfg.dense,
                   gamma=cfg.gamma, num_envs=num_envs)

    def sparse(self, batch: StepBatch) -> np.ndarray:
        return (batch.done_prob.cpu().numpy() >= self.theta).astype(np.float64)

    def similarity(self, batch: StepBatch) -> np.ndarray:
        return 1.0 - self.distance(batch.third, batch.wrist, batch.goal_index)

    def reset(self, rows: np.ndarray, batch: StepBatch) -> None:
        if not len(rows) or not self.needs_frames:
            return
        if len(batch.goal_index) != len(rows):
            raise ValueError(f"reset: {len(rows)} restarted rows but a batch of {len(batch.goal_index)} first frames")
        if self.dense_kind == "potential":
            self.prev_phi[rows] = -self.distance(batch.third, batch.wrist, batch.goal_index)
        elif self.dense_kind == "progress":
            feats = self.distance.features(batch.third, batch.wrist)  # per view, per layer (len(rows), C, h, w)
            if self.start_feats is None:
                self.start_feats = [[f.new_zeros((self.num_envs, *f.shape[1:])) for f in view] for view in feats]
            idx = torch.as_tensor(rows, dtype=torch.long)
            for store, view in zip(self.start_feats, feats):
                for s, f in zip(store, view):
                    s[idx.to(s.device)] = f

    def progress(self, feats: list[list[torch.Tensor]], start: list[list[torch.Tensor]], goal_index) -> np.ndarray:
        """(B,) LPIPS to the episode's first frame minus LPIPS to the goal."""
        return self.distance.between(feats, start) - self.distance.between(feats, self.distance.goals_of(goal_index))

    def __call__(self, batch: StepBatch) -> np.ndarray:
        if not self.needs_frames:
            return self.alpha * self.sparse(batch)
        if self.dense_kind == "similarity":
            dense = self.similarity(batch)
        elif self.dense_kind == "progress":
            if self.start_feats is None:
                raise RuntimeError("dense: progress needs reset() with the episodes' first frames before a step")
            dense = self.progress(self.distance.features(batch.third, batch.wrist), self.start_feats, batch.goal_index)
        else:
            phi = -self.distance(batch.third, batch.wrist, batch.goal_index)
            dense = self.gamma * phi - self.prev_phi
            self.prev_phi = phi
        return self.alpha * self.sparse(batch) + self.beta * dense

    def dense_along(self, first: StepBatch, frames: StepBatch) -> np.ndarray:
        """The dense term (T,) along one episode, all frames scored in one batch."""
        third, wrist = torch.cat([first.third, frames.third]), torch.cat([first.wrist, frames.wrist])
        if self.dense_kind == "progress":
            feats = self.distance.features(third, wrist)  # per view, per layer (T+1, C, h, w)
            now = [[f[1:] for f in view] for view in feats]
            start = [[f[:1].expand_as(f[1:]) for f in view] for view in feats]
            return self.progress(now, start, frames.goal_index)
        d = self.distance(third, wrist, np.concatenate([first.goal_index, frames.goal_index]))  # (T+1,)
        return 1.0 - d[1:] if self.dense_kind == "similarity" else self.gamma * -d[1:] + d[:-1]

    def along(self, first: StepBatch, frames: StepBatch) -> np.ndarray:
        if not self.needs_frames:
            return self.alpha * self.sparse(frames)
        return self.alpha * self.sparse(frames) + self.beta * self.dense_along(first, frames)
