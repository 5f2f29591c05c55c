"""A tiny in-memory stand-in for ``stages.collect.dataset.Dataset`` with the same interface.

Frames are synthetic but structured: a coloured square (the "object") moves over a plain
background in the third view; the wrist view shows a zoomed, shifted copy. OOD episodes use an
object colour never seen in IND episodes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FakeEpisodeMeta:
    episode_id: str
    task: str
    instruction: str
    scene_id: str
    object: str
    container: str
    table: str
    split: str
    kind: str
    seed: int
    success: bool
    length: int
    shard: int


@dataclass
class FakeEpisode:
    third: np.ndarray  # (T+1, H, W, 3) uint8
    wrist: np.ndarray  # (T+1, H, W, 3) uint8
    action: np.ndarray  # (T, 7) float32


IND_COLORS = [(220, 40, 40), (40, 200, 60), (40, 80, 220), (230, 200, 40)]
OOD_COLORS = [(200, 60, 220)]


def render(color, x: float, y: float, size: int, bg=(120, 110, 100)) -> np.ndarray:
    """(size, size, 3) uint8: a 1/4-size square of ``color`` with its corner at fraction (x, y)."""
    img = np.empty((size, size, 3), np.uint8)
    img[:] = bg
    img[size // 2 :, :, :] = (150, 140, 120)  # the "table"
    s = size // 4
    r, c = int(y * (size - s)), int(x * (size - s))
    img[r : r + s, c : c + s] = color
    return img


class FakeDataset:
    """``n_ind`` + ``n_ood`` episodes of length ``T`` at ``size`` x ``size`` pixels."""

    def __init__(self, n_ind: int = 6, n_ood: int = 2, T: int = 9, size: int = 64, seed: int = 0):
        rng = np.random.default_rng(seed)
        self._eps, self.episodes = {}, []
        for i in range(n_ind + n_ood):
            split = "ind" if i < n_ind else "ood"
            color = IND_COLORS[i % len(IND_COLORS)] if split == "ind" else OOD_COLORS[0]
            x0, y0, dx, dy = rng.uniform(0, 1), rng.uniform(0, 1), rng.uniform(-0.08, 0.08), rng.uniform(-0.08, 0.08)
            t = np.arange(T + 1)
            xs, ys = np.clip(x0 + dx * t, 0, 1), np.clip(y0 + dy * t, 0, 1)
            third = np.stack([render(color, x, y, size) for x, y in zip(xs, ys)])
            wrist = np.stack([render(color, 1 - x, 0.5 * y + 0.5, size, bg=(60, 60, 70)) for x, y in zip(xs, ys)])
            eid = f"ep{i:03d}"
            self._eps[eid] = FakeEpisode(third, wrist, rng.normal(size=(T, 7)).astype(np.float32))
            self.episodes.append(FakeEpisodeMeta(eid, "push", "push the cube", f"s{i}", "cube", "plate", "wood", split, "optimal", i, True, T, 0))

    def load(self, episode_id: str) -> FakeEpisode:
        return self._eps[episode_id]


def write_collect_artifact(root, fake: FakeDataset):
    """Write ``fake``'s episodes as a real collect artifact (MCAP shard + episode index) under ``root``."""
    from pathlib import Path

    from stages.collect.dataset import SHARD_DIR, EpisodeMeta, write_index
    from stages.collect.mcap_io import ShardWriter

    root = Path(root)
    (root / SHARD_DIR).mkdir(parents=True)
    writer = ShardWriter(root / SHARD_DIR / "shard-000.mcap")
    metas = []
    for m in fake.episodes:
        ep = fake.load(m.episode_id)
        T = m.length
        meta = {**m.__dict__, "shard": "shard-000.mcap"}
        arrays = {
            "third": ep.third, "wrist": ep.wrist, "action": ep.action,
            "ee_pose": np.zeros((T + 1, 7), np.float32), "qpos": np.zeros((T + 1, 9), np.float32),
            "reward": np.zeros(T, np.float32), "success": np.zeros(T + 1, bool),
        }
        start, end = writer.write_episode(meta, arrays)
        metas.append(EpisodeMeta.from_dict({**meta, "start_ns": start, "end_ns": end}))
    writer.close()
    write_index(root, metas)
    return root
