"""Token arrays of every episode: one memory-mapped ``tokens.npy`` plus ``index.json``.

    tokens.npy   uint16 (N_frames, h, w): every frame of every episode, episodes back to back
    index.json   {"grid": [h, w], "bits": b, "episodes": {episode_id: [offset, length]}}

    store = TokenStore(tokenize_artifact_dir)
    store.episode(episode_id)  # (T+1, h, w) uint16 view into the memory map, no copy
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

TOKENS = "tokens.npy"
INDEX = "index.json"


class TokenStore:
    """Read-only access to the token arrays of a tokenize artifact."""

    def __init__(self, directory: str | Path):
        directory = Path(directory)
        for name in (TOKENS, INDEX):
            if not (directory / name).is_file():
                raise FileNotFoundError(f"{directory / name} is missing: is {directory} a committed tokenize artifact?")
        meta = json.loads((directory / INDEX).read_text())
        self.grid: tuple[int, int] = tuple(meta["grid"])
        self.bits: int = int(meta["bits"])
        self.offsets: dict[str, tuple[int, int]] = {k: (int(o), int(n)) for k, (o, n) in meta["episodes"].items()}
        self.tokens = np.load(directory / TOKENS, mmap_mode="r")  # (N_frames, h, w) uint16

    @property
    def episode_ids(self) -> list[str]:
        return list(self.offsets)

    def __len__(self) -> int:
        return len(self.offsets)

    def __contains__(self, episode_id: str) -> bool:
        return str(episode_id) in self.offsets

    def episode(self, episode_id: str) -> np.ndarray:
        """Tokens of one episode, (T+1, h, w) uint16 (a view into the memory map)."""
        try:
            offset, length = self.offsets[str(episode_id)]
        except KeyError:
            raise KeyError(f"episode {episode_id!r} is not in this token store ({len(self.offsets)} episodes)") from None
        return self.tokens[offset : offset + length]


def write_index(directory: Path, grid: tuple[int, int], bits: int, offsets: dict[str, tuple[int, int]]) -> None:
    """Write ``index.json`` for a token array laid out as ``offsets`` says."""
    meta = {"grid": list(grid), "bits": bits, "episodes": {k: list(v) for k, v in offsets.items()}}
    (Path(directory) / INDEX).write_text(json.dumps(meta, indent=1) + "\n")
