"""The calibration gate: PPO trains in the world model only on the tasks where the model imagines the
starting policy succeeding about as often as it really does.

wm_play's play (``play.json``) says how often the SFT policy really succeeds, closed loop in ManiSkill
on IND training environments, per task. Before PPO the same policy (deterministic actions) acts on its
own imagined frames from ``starts_per_task`` training starts of each task, for the rl stage's horizon,
and the done head (>= the env's ``theta_done``) says how often it imagines success. A task whose
imagined rate is below ``ratio`` x its real rate (the model cannot show the policy succeeding where it
does, so PPO there is paid by the dense term alone) or above real rate / ``ratio`` (it shows successes
that do not happen, which PPO learns to chase) is left out of PPO's environments; the multi-task
policy keeps acting on it with what SFT taught it. Measured at HEAD, seed 0 (docs/RESULTS.md): the SFT
policy imagined 0 of 12 pick-and-place successes against 46 of 96 real ones, and PPO in that model
gave pick-and-place up (-0.36 in domain).

Spends world-model steps only (no simulator step: the real rates are wm_play's), and reads no OOD
environment.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stages.rl.imagined import closed_loop


@dataclass
class TaskCalibration:
    task: str
    imagined: int  # starts whose imagined episode the done head ended as a success
    starts: int
    real: int  # successful play episodes of the task (wm_play)
    played: int

    @property
    def imagined_rate(self) -> float:
        return self.imagined / self.starts

    @property
    def real_rate(self) -> float:
        return self.real / self.played

    def kept(self, ratio: float) -> bool:
        """Imagined rate within [ratio, 1 / ratio] x the real rate (a task never solved in play is kept
        only if it is never imagined solved either)."""
        lo, hi = ratio * self.real_rate, self.real_rate / ratio
        return lo <= self.imagined_rate <= hi

    def row(self, ratio: float) -> dict:
        return {"task": self.task, "imagined": self.imagined, "starts": self.starts, "real": self.real,
                "played": self.played, "imagined_rate": self.imagined_rate, "real_rate": self.real_rate,
                "kept": self.kept(ratio)}


def real_rates(play: list[dict], tasks: list[str]) -> dict[str, tuple[int, int]]:
    """{task: (successes, episodes)} of wm_play's play rows (``env_id`` is ``task/scene``)."""
    out = {t: [0, 0] for t in tasks}
    for r in play:
        task = r["env_id"].split("/", 1)[0]
        if task in out:
            out[task][0] += int(bool(r["success"]))
            out[task][1] += 1
    missing = [t for t, (_, n) in out.items() if n == 0]
    if missing:
        raise ValueError(f"wm_play's play has no episode of tasks {missing}: the calibration gate needs the SFT "
                         "policy's real success rate on every task it trains (raise wm_play.episodes)")
    return {t: (s, n) for t, (s, n) in out.items()}


@torch.no_grad()
def imagined_successes(policy, wm, obs_fn, starts: list, steps: int, theta: float, batch: int = 32,
                       persist: int = 1) -> np.ndarray:
    """(N,) bool: whether the done head stayed at or above ``theta`` for ``persist`` consecutive steps within
    ``steps`` imagined steps of ``policy`` from each ``stages.rl.wm_env.Start``."""
    done = np.zeros(len(starts), bool)
    for lo in range(0, len(starts), batch):
        chunk = starts[lo:lo + batch]
        tokens = torch.as_tensor(np.stack([s.tokens for s in chunk]))  # (B, h, w)
        proprio = np.stack([s.proprio for s in chunk])  # (B, 10)
        held = np.zeros(len(chunk), np.int64)  # (B,) consecutive steps at or above theta
        for s in closed_loop(policy, wm, obs_fn, tokens, proprio, [s.instruction for s in chunk], steps):
            held = np.where(s.out.done_prob.float().cpu().numpy() >= theta, held + 1, 0)
            done[lo:lo + len(chunk)] |= held >= persist
    return done


def calibrate(policy, wm, obs_fn, starts_by_task: dict[str, list], play: list[dict], steps: int, theta: float,
              per_task: int, seed: int, progress=None, persist: int = 1) -> list[TaskCalibration]:
    """One ``TaskCalibration`` per task of ``starts_by_task`` ({task: [Start, ...]}), from ``per_task``
    starts of each (a seeded choice) and the play's real rates; ``progress`` (a bar) advances per task."""
    rates = real_rates(play, list(starts_by_task))
    rng = np.random.default_rng(seed)
    out = []
    policy.set_training_mode(False)
    for task, starts in starts_by_task.items():
        if not starts:
            raise ValueError(f"task {task!r} has no training start to calibrate on")
        pick = [starts[i] for i in sorted(rng.choice(len(starts), size=min(per_task, len(starts)), replace=False))]
        done = imagined_successes(policy, wm, obs_fn, pick, steps, theta, persist=persist)
        out.append(TaskCalibration(task, int(done.sum()), len(pick), *rates[task]))
        if progress is not None:
            progress.update(1)
    return out
