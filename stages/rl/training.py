"""PPO bookkeeping: episode statistics, policy snapshots over wall time, the training-curve plot.

Success over training is binned by the step an episode *started* at, over the episodes no unfinished
episode started before (``uncensored``): a successful episode is short (it ends when the task is
done, a failure at the step cap), so in the order episodes end the first ones are mostly successes
and a curve by end time starts too high.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from stages.evaluate.stats import wilson


class TrainingLog(BaseCallback):
    """Per-episode return/length/termination, and ``snapshots`` policy checkpoints spread over training."""

    def __init__(self, out: Path, total_timesteps: int, snapshots: int, progress=None, curves=None):
        super().__init__()
        self.out, self.progress, self.curves = Path(out), progress, curves
        self.marks = sorted({int(total_timesteps * (i + 1) / snapshots) for i in range(snapshots)}) if snapshots else []
        self.episodes: list[dict] = []
        self.snapshots: list[dict] = []
        self._ret = self._len = self._start = None
        self._t0 = time.perf_counter()
        self._last = 0

    def _on_training_start(self) -> None:
        n = self.training_env.num_envs
        self._ret, self._len = np.zeros(n), np.zeros(n, dtype=int)
        self._start = np.full(n, int(self.num_timesteps), dtype=np.int64)  # (n,) step each env's episode began at
        self._t0 = time.perf_counter()

    def _on_step(self) -> bool:
        dones, infos = self.locals["dones"], self.locals["infos"]
        # the environment's own reward, before VecNormalize scaled it for the update
        original = getattr(self.training_env, "get_original_reward", None)
        rewards = original() if original is not None else self.locals["rewards"]
        self._ret += rewards
        self._len += 1
        for i in np.nonzero(dones)[0]:
            info = infos[i]
            terminated, success = episode_outcome(info)
            self.episodes.append({"t": int(self.num_timesteps), "start": int(self._start[i]), "wall": time.perf_counter() - self._t0,
                                  "return": float(self._ret[i]), "length": int(self._len[i]),
                                  "terminated": terminated, "success": success,
                                  "env": info.get("env", ""), "task": task_of(info.get("env", ""))})
            if self.curves is not None:
                self.curves.scalar("episode/return", self._ret[i], self.num_timesteps)
                self.curves.scalar("episode/length", self._len[i], self.num_timesteps)
                self.curves.scalar("episode/terminated", float(terminated), self.num_timesteps)
            self._ret[i], self._len[i], self._start[i] = 0.0, 0, self.num_timesteps
        if self.progress is not None:
            self.progress.update(self.num_timesteps - self._last)
            self._last = self.num_timesteps
        while self.marks and self.num_timesteps >= self.marks[0]:
            step = self.marks.pop(0)
            path = self.out / "snapshots" / f"step_{step:08d}.zip"
            path.parent.mkdir(parents=True, exist_ok=True)
            self.model.save(path)
            self.snapshots.append({"timesteps": step, "wall_seconds": time.perf_counter() - self._t0,
                                   "path": str(path.relative_to(self.out))})
        return True

    def unfinished_from(self) -> int:
        """The step the earliest still-running episode started at (every episode started before it ended)."""
        return int(self._start.min()) if self._start is not None else int(self.num_timesteps)

    def write(self) -> None:
        write_episode_files(self.out, self.episodes, self.unfinished_from(), self.snapshots)

    def summary(self, window: int = 50) -> dict:
        return summary(self.episodes, self.unfinished_from(), window)


def episode_outcome(info: dict) -> tuple[bool, bool]:
    """(terminated, success) of the episode a VecEnv step ended: the world model's done head ended it, or
    the simulator (which says whether it succeeded; a world-model episode succeeds when its done head ends it)."""
    terminated = bool(info.get("terminated_by_done_head", not info.get("TimeLimit.truncated", False)))
    return terminated, bool(info.get("success", terminated))


def write_episode_files(out: Path, episodes: list[dict], unfinished_from: int, snapshots: list[dict]) -> None:
    """``snapshots/index.json``, ``episodes.json`` and ``success_by_start.json`` (module docstring)."""
    out = Path(out)
    (out / "snapshots").mkdir(parents=True, exist_ok=True)
    (out / "snapshots" / "index.json").write_text(json.dumps(snapshots, indent=1) + "\n")
    (out / "episodes.json").write_text(json.dumps(episodes) + "\n")
    (out / "success_by_start.json").write_text(json.dumps(
        {"unfinished_from": unfinished_from, "bins": success_by_start(episodes, unfinished_from),
         "by_task": success_by_task(episodes, unfinished_from)},
        indent=1) + "\n")


def summary(episodes: list[dict], unfinished_from: int, window: int = 50) -> dict:
    """Episode count, success in the first and last fifth by start step, terminated fraction, return and length."""
    eps = episodes
    if not eps:
        return {"episodes": 0}
    last = eps[-window:]
    first = eps[:window]
    fifths = success_by_start(eps, unfinished_from, bins=5)
    return {"episodes": len(eps), "success_first_fifth": fifths[0]["success"] if fifths else None,
            "success_last_fifth": fifths[-1]["success"] if fifths else None, "terminated_fraction": float(np.mean([e["terminated"] for e in eps])),
            "return_first": float(np.mean([e["return"] for e in first])),
            "return_last": float(np.mean([e["return"] for e in last])),
            "length_last": float(np.mean([e["length"] for e in last]))}


def task_of(env: str) -> str:
    """The task of an environment key "<task>/<scene_id>" ("" for an unknown environment)."""
    return env.split("/", 1)[0] if env else ""


def uncensored(episodes: list[dict], unfinished_from: int) -> list[dict]:
    """The episodes that started before ``unfinished_from``: of those, every one that began has ended."""
    return [e for e in episodes if e["start"] < unfinished_from]


def success_by_start(episodes: list[dict], unfinished_from: int, bins: int = 10) -> list[dict]:
    """Success rate of the uncensored episodes in ``bins`` equal spans of their start step, each with its
    count and 95% Wilson interval; empty spans are left out."""
    eps = uncensored(episodes, unfinished_from)
    if not eps:
        return []
    edges = np.linspace(0, unfinished_from, bins + 1)  # (bins + 1,) start-step edges
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        s = [e["success"] for e in eps if lo <= e["start"] < hi]
        if s:
            rate, low, high = wilson(int(sum(s)), len(s))
            out.append({"start_from": int(lo), "start_to": int(hi), "episodes": len(s), "success": rate,
                        "interval": [low, high]})
    return out


def success_by_task(episodes: list[dict], unfinished_from: int, bins: int = 5) -> dict[str, list[dict]]:
    """``success_by_start`` per task (fewer spans: a task has a quarter of the episodes); episodes with no
    task recorded are left out."""
    tasks = sorted({e.get("task", "") for e in episodes} - {""})
    return {t: success_by_start([e for e in episodes if e.get("task") == t], unfinished_from, bins) for t in tasks}


def plot_training(episodes: list[dict], path: Path, title: str, unfinished_from: int | None = None) -> None:
    """Episode return over env steps; with ``unfinished_from``, a second panel: success by start step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2 if unfinished_from is not None else 1, figsize=(9 if unfinished_from is not None else 5, 3),
                             squeeze=False)
    ax = axes[0, 0]
    if episodes:
        t = np.array([e["t"] for e in episodes])
        r = np.array([e["return"] for e in episodes])
        k = max(1, len(r) // 20)
        smooth = np.convolve(r, np.ones(k) / k, mode="valid")
        ax.plot(t, r, ".", ms=2, alpha=0.3)
        ax.plot(t[k - 1:], smooth)
    ax.set_xlabel("env steps")
    ax.set_ylabel("episode return")
    ax.set_title(title, fontsize=9)
    if unfinished_from is not None:
        ax = axes[0, 1]
        b = success_by_start(episodes, unfinished_from)
        if b:
            mid = np.array([(x["start_from"] + x["start_to"]) / 2 for x in b])
            rate = np.array([x["success"] for x in b])
            lo, hi = np.array([x["interval"] for x in b]).T  # (bins,) each
            ax.fill_between(mid, lo, hi, alpha=0.2)
            ax.plot(mid, rate, "o-", ms=3, color="k", label="all")
            for task, tb in success_by_task(episodes, unfinished_from).items():
                if tb:
                    ax.plot([(x["start_from"] + x["start_to"]) / 2 for x in tb], [x["success"] for x in tb], ".-", lw=0.8,
                            ms=3, alpha=0.8, label=task)
            ax.legend(fontsize=6, loc="best", ncol=2)
        ax.set_ylim(0, 1)
        ax.set_xlabel("env step the episode started at")
        ax.set_ylabel("training success (95% Wilson)")
        ax.set_title("episodes that started before any unfinished one", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
