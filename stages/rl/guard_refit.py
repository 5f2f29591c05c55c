"""The guard refitted on imagined episodes the simulator has checked (``rl.guard_replay_rounds``).

Beyond the paper and beyond the plain guard (``stages.rl.guard``): the done head and the guard
learn "success" from recorded data, and PPO finds frames the world model imagines as successes
where the simulator disagrees (imagined-success precision, ``stages.rl.imagined``). Here, during
PPO, ``rounds`` times at evenly spaced steps, the current policy imagines episodes from fresh
simulator starts of IND *training* environments; ManiSkill replays the actions; every imagined
step becomes a labelled frame for the guard's ensemble: the step at which the replay first
succeeds is a positive, every step before it a negative (a replay that never succeeds: all its
steps are negatives). The ensemble is refitted on the recorded frames plus all replayed ones so
far and replaces the environment's guard, so a success needs its confirmation from then on.

Cost in simulator steps: ``rounds * envs * max_episode_steps`` policy steps at most (each
``frame_skip`` control steps), reported as ``guard/replay/sim_policy_steps``. The replays' seeds
start at ``SEED_BASE``, apart from the precision metric's (which also covers OOD scenes) and
evaluation's.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback

from stages.rl.guard import Guard, fit_done_ensemble
from stages.rl.imagined import Replay, precision_metrics

SEED_BASE = 4_000_000  # replay seeds: apart from training (seed), precision (3e6) and evaluation


def replay_labels(rows: list[Replay], hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Labelled imagined frames from replays. hidden (N, T, D) -> frames (M, D), success (M,) bool.

    Row i contributes its first ``first_success`` steps (the last one positive) if the replay
    succeeded, else all T steps as negatives: what the simulator says of the steps it checked.
    """
    if len(rows) != hidden.shape[0]:
        raise ValueError(f"{len(rows)} replay rows but hidden states of {hidden.shape[0]} episodes")
    frames, labels = [], []
    for i, r in enumerate(rows):
        n = r.first_success if r.first_success > 0 else hidden.shape[1]
        frames.append(hidden[i, :n].cpu())  # beside the CPU copy of the recorded frames
        y = torch.zeros(n, dtype=torch.bool)
        y[n - 1] = r.first_success > 0
        labels.append(y)
    return torch.cat(frames), torch.cat(labels)


class GuardRefit(BaseCallback):
    """After the PPO rollout that crosses each of ``rounds`` evenly spaced steps, refit the env's guard.

    imagine(policy, round) -> (rows, hidden (N, T, D)): the imagined-and-replayed episodes.
    base_hidden (M, D), base_success (M,): the recorded frames the guard was first fitted on.
    """

    def __init__(self, env, imagine: Callable, base_hidden: torch.Tensor, base_success: torch.Tensor, *,
                 total_timesteps: int, rounds: int, heads: int, steps: int, lr: float, seed: int,
                 coef: float, theta: float, device: str = "cpu", log=None):
        super().__init__()
        self.env, self.imagine, self.rounds = env, imagine, rounds
        self.hidden, self.success = base_hidden.float(), base_success.bool()
        self.base_frames = len(self.success)
        self.at = [total_timesteps * (k + 1) // (rounds + 1) for k in range(rounds)]  # PPO steps of each refit
        self.fit = dict(heads=heads, steps=steps, lr=lr, device=device)
        self.seed, self.coef, self.theta, self.log = seed, coef, theta, log
        self.history: list[dict] = []  # per round: what the replays said before that refit
        self.sim_policy_steps = 0

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        k = len(self.history)
        if k >= self.rounds or self.num_timesteps < self.at[k]:
            return
        rows, hidden = self.imagine(self.model.policy, k)
        self.sim_policy_steps += sum(r.first_success if r.first_success > 0 else hidden.shape[1] for r in rows)
        x, y = replay_labels(rows, hidden)
        self.hidden, self.success = torch.cat([self.hidden, x]), torch.cat([self.success, y])
        ensemble, losses = fit_done_ensemble(self.hidden, self.success, seed=self.seed + 1 + k, **self.fit)
        self.env.guard = Guard(ensemble, self.coef, self.theta)
        stats = {"timesteps": int(self.num_timesteps), **precision_metrics(rows),
                 "frames_added": int(len(y)), "positives_added": int(y.sum()), "final_bce": float(np.mean(losses[-20:]))}
        self.history.append(stats)
        if self.log is not None:
            self.log.info("rl: guard refit %d/%d at %d steps: %s", k + 1, self.rounds, self.num_timesteps, stats)

    def metrics(self) -> dict:
        out: dict = {"guard/replay/rounds_done": len(self.history), "guard/replay/sim_policy_steps": self.sim_policy_steps,
                     "guard/replay/frames": int(len(self.success) - self.base_frames),
                     "guard/replay/positive_frames": int(self.success[self.base_frames:].sum())}
        for k, stats in enumerate(self.history):
            out.update({f"guard/replay/round{k + 1}/{name}": v for name, v in stats.items()})
        return out
