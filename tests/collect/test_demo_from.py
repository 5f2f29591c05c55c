"""SFT imitates a recovery episode from its ``demo_from`` on: the deliberate mistake is never a pair."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from stages.sft.data import load_demo


def _episode(T: int, demo_from: int):
    rng = np.random.default_rng(0)
    xyz = np.cumsum(np.full((T + 1, 3), 0.01), axis=0)  # (T+1, 3) the TCP moves 1.7 cm per control step
    ee = np.concatenate([xyz, np.tile([1.0, 0.0, 0.0, 0.0], (T + 1, 1))], 1).astype(np.float32)  # (T+1, 7)
    actions = rng.uniform(-0.5, 0.5, (T, 7)).astype(np.float32)
    actions[:, 6] = 1.0
    actions[:demo_from, :6] = 0.9  # the mistake: an action SFT must never see
    states = {"ee_pose": ee, "qpos": np.zeros((T + 1, 9), np.float32), "action": actions}
    meta = SimpleNamespace(length=T, instruction="x", demo_from=demo_from)
    ds = SimpleNamespace(meta=lambda _: meta, load_states=lambda _: states)
    store = SimpleNamespace(episode=lambda _: np.arange(T + 1)[:, None, None] * np.ones((1, 2, 2), np.int64))
    return ds, store


@pytest.mark.parametrize("min_move", [0.0, 0.03])
def test_a_recovery_episode_is_imitated_from_the_end_of_its_mistake(min_move):
    T, s = 40, 13
    ds, store = _episode(T, s)
    demo = load_demo(ds, store, "e", frame_skip=4, min_move=min_move)
    assert demo.tokens[0, 0, 0] == s  # the first kept frame is the one after the mistake
    assert demo.tokens[-1, 0, 0] == T and len(demo.actions) == len(demo.tokens) - 1
    assert not np.any(np.isclose(demo.actions[:, :6], 0.9))  # no mistake action, composed or not
    whole = load_demo(*_episode(T, 0), "e", frame_skip=4, min_move=min_move)
    assert whole.tokens[0, 0, 0] == 0 and len(whole.actions) > len(demo.actions)  # demo_from 0: every frame
