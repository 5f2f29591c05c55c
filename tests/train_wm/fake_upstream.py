"""Tiny collect and tokenize artifacts for train_wm tests.

Collect is faked in memory (a module standing in for ``stages.collect.dataset``): a coloured square
moves by the first two action dims; success once it is in the right quarter of the image. Tokenize
is real code: an untrained ``TokenizerNet`` saved with ``save_checkpoint`` and its tokens written
with the real ``TokenStore`` layout.
"""
from __future__ import annotations

import json
import types
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

SIZE = 32


@dataclass(frozen=True)
class Meta:
    episode_id: str
    task: str
    instruction: str
    scene_id: str
    split: str
    kind: str
    success: bool
    length: int


@dataclass
class Ep:
    third: np.ndarray  # (T+1, H, W, 3) uint8
    wrist: np.ndarray
    action: np.ndarray  # (T, 7)
    success: np.ndarray  # (T+1,) bool
    pos: np.ndarray  # (T+1, 2) the square's position, which the fake robot's TCP follows


def _render(x: float, y: float, color) -> np.ndarray:
    img = np.full((SIZE, SIZE, 3), 110, np.uint8)
    s = SIZE // 4
    r, c = int(y * (SIZE - s)), int(x * (SIZE - s))
    img[r : r + s, c : c + s] = color
    return img


class FakeDataset:
    """IND and OOD episodes of length T whose motion follows the actions."""

    def __init__(self, directory=None, n_ind: int = 8, n_ood: int = 2, T: int = 36, seed: int = 0):
        rng = np.random.default_rng(seed)
        self._eps, self.episodes = {}, []
        for i in range(n_ind + n_ood):
            split = "ind" if i < n_ind else "ood"
            color = (220, 40, 40) if split == "ind" else (40, 40, 220)
            act = np.zeros((T, 7), np.float32)
            act[:, :6] = rng.uniform(-1, 1, size=(T, 6))
            act[:, 6] = rng.choice([-1.0, 1.0], size=T)
            pos = np.zeros((T + 1, 2))
            pos[0] = rng.uniform(0.1, 0.6, size=2)
            for t in range(T):
                pos[t + 1] = np.clip(pos[t] + 0.08 * act[t, :2], 0, 1)
            third = np.stack([_render(x, y, color) for x, y in pos])
            wrist = np.stack([_render(1 - x, y, color) for x, y in pos])
            success = pos[:, 0] > 0.6
            eid = f"ep{i:03d}"
            instr = ["push the red cube", "pull the red cube"][i % 2] if split == "ind" else "push the blue cube"
            self._eps[eid] = Ep(third, wrist, act, success, pos)
            self.episodes.append(Meta(eid, "push", instr, f"s{i}", split, "optimal", bool(success[-1]), T))

    def load(self, episode_id: str) -> Ep:
        return self._eps[episode_id]

    def load_states(self, episode_id: str) -> dict:
        """The real Dataset's image-free view: a TCP that follows the square, fingers open."""
        ep = self._eps[episode_id]
        n = len(ep.pos)
        ee = np.zeros((n, 7), np.float32)
        ee[:, :2], ee[:, 2], ee[:, 4] = 0.3 * ep.pos, 0.15, 1.0
        qpos = np.zeros((n, 9), np.float32)
        qpos[:, 7:] = 0.04
        return {"ee_pose": ee, "qpos": qpos, "success": ep.success, "action": ep.action,
                "reward": np.zeros(len(ep.action), np.float32)}


def install_fake_collect(monkeypatch) -> None:
    """Make ``from stages.collect.dataset import Dataset`` return ``FakeDataset``."""
    mod = types.ModuleType("stages.collect.dataset")
    mod.Dataset = FakeDataset
    monkeypatch.setitem(__import__("sys").modules, "stages.collect.dataset", mod)


def make_tokenize_artifact(directory: Path, ds: FakeDataset, bits: int = 6) -> Path:
    """An untrained tokenizer (32 px, 8x8 grid) plus the token store of every episode of ``ds``."""
    from stages.tokenize.model import ModelSpec, TokenizerNet
    from stages.tokenize.store import TOKENS, write_index
    from stages.tokenize.tokenizer import load_tokenizer, save_checkpoint

    directory.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    save_checkpoint(TokenizerNet(ModelSpec(image_size=SIZE, bits=bits, channels=(8, 16), res_blocks=1)), directory)
    tok = load_tokenizer(directory)
    chunks, offsets, off = [], {}, 0
    for meta in ds.episodes:
        ep = ds.load(meta.episode_id)
        t = tok.encode(ep.third, ep.wrist).numpy().astype(np.uint16)
        chunks.append(t)
        offsets[meta.episode_id] = (off, len(t))
        off += len(t)
    np.save(directory / TOKENS, np.concatenate(chunks))
    write_index(directory, tok.grid, bits, offsets)
    ind = [m.episode_id for m in ds.episodes if m.split == "ind"]
    (directory / "split.json").write_text(json.dumps({"train": ind[1:], "heldout": ind[:1]}))
    return directory
