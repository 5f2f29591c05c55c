"""The direct goal predictor: one-step clips from early frames to the last, trained and decoded."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from stages.goals.direct import jump_clips, predict_goals, train_goal_predictor


class FakeStore:
    """Episodes of 9 frames on a 2x2 grid: every token counts up by one per frame."""

    def episode(self, episode_id: str) -> np.ndarray:
        base = int(episode_id[-1])
        return np.stack([np.full((2, 2), base + t) for t in range(9)])  # (T+1, h, w)


def _meta(i: int):
    return SimpleNamespace(episode_id=f"ep{i}", instruction=f"task {i % 2}", split="ind", kind="optimal")


def test_jump_clips_pair_early_frames_with_the_last():
    clips = jump_clips(FakeStore(), [_meta(1)], early=(0.0, 0.25))
    assert [c.episode_id for c in clips] == ["ep1@0", "ep1@2"]
    assert clips[1].tokens.shape == (2, 4) and (clips[1].tokens[0] == 3).all() and (clips[1].tokens[1] == 9).all()
    assert clips[0].length == 1 and clips[0].done.tolist() == [0.0, 1.0]


def test_the_predictor_learns_the_jump_and_decodes_goals():
    store = FakeStore()
    clips = jump_clips(store, [_meta(i) for i in range(4)])
    text = {f"task {k}": np.random.default_rng(k).normal(size=384).astype(np.float32) for k in range(2)}
    net, result = train_goal_predictor(clips, text, vocab=16, grid=(2, 2), dim=32, depth=1, steps=150, batch_size=8,
                                       lr=3e-3, seed=0, device="cpu")
    first, last = result["history"][0]["ce"], result["final"]["ce"]
    assert last < 0.5 * first
    goals = predict_goals(net, torch.as_tensor(np.stack([store.episode(f"ep{i}")[0] for i in range(4)])),
                          ["task 0", "task 1", "task 0", "task 1"], text, decode_steps=2)
    assert goals.shape == (4, 2, 2)
    assert (goals == np.arange(8, 12)[:, None, None]).mean() > 0.5  # most tokens of the real last frames
