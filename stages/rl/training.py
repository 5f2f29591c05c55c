"""PPO bookkeeping: episode statistics, policy snapshots over wall time, the training-curve plot."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback


class TrainingLog(BaseCallback):
    """Per-episode return/length/termination, and ``snapshots`` policy checkpoints spread over training."""

    def __init__(self, out: Path, total_timesteps: int, snapshots: int, progress=None, curves=None):
        super().__init__()
        self.out, self.progress, self.curves = Path(out), progress, curves
        self.marks = sorted({int(total_timesteps * (i + 1) / snapshots) for i in range(snapshots)}) if snapshots else []
        self.episodes: list[dict] = []
        self.snapshots: list[dict] = []
        self._ret = self._len = None
        self._t0 = time.perf_counter()
        self._last = 0

    def _on_training_start(self) -> None:
        n = self.training_env.num_envs
        self._ret, self._len = np.zeros(n), np.zeros(n, dtype=int)
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
            terminated = info.get("terminated_by_done_head", not info.get("TimeLimit.truncated", False))
            self.episodes.append({"t": int(self.num_timesteps), "wall": time.perf_counter() - self._t0,
                                  "return": float(self._ret[i]), "length": int(self._len[i]),
                                  "terminated": bool(terminated), "success": bool(info.get("success", terminated))})
            if self.curves is not None:
                self.curves.scalar("episode/return", self._ret[i], self.num_timesteps)
                self.curves.scalar("episode/length", self._len[i], self.num_timesteps)
                self.curves.scalar("episode/terminated", float(terminated), self.num_timesteps)
            self._ret[i], self._len[i] = 0.0, 0
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

    def write(self) -> None:
        (self.out / "snapshots").mkdir(parents=True, exist_ok=True)
        (self.out / "snapshots" / "index.json").write_text(json.dumps(self.snapshots, indent=1) + "\n")
        (self.out / "episodes.json").write_text(json.dumps(self.episodes) + "\n")

    def summary(self, window: int = 50) -> dict:
        eps = self.episodes
        if not eps:
            return {"episodes": 0}
        last = eps[-window:]
        first = eps[:window]
        return {"episodes": len(eps), "terminated_fraction": float(np.mean([e["terminated"] for e in eps])),
                "return_first": float(np.mean([e["return"] for e in first])),
                "return_last": float(np.mean([e["return"] for e in last])),
                "length_last": float(np.mean([e["length"] for e in last]))}


def plot_training(episodes: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3))
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
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
