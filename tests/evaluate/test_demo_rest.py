"""scripts/demo_rest.py: the evaluate stage's came-to-rest measure applied to demonstrations as SFT reads them."""
from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
from demo_rest import demo_rest  # noqa: E402

from stages.evaluate.episodes import REST_ACTION, REST_STEPS  # noqa: E402


def _dataset(episodes):
    """episodes: {id: (task, (T, 7) control actions)}; the TCP follows the actions' position dims."""
    metas, states = {}, {}
    for i, (task, actions) in episodes.items():
        T = len(actions)
        xyz = np.concatenate([np.zeros((1, 3)), np.cumsum(actions[:, :3] * 0.01, axis=0)])  # (T+1, 3) metres
        ee = np.concatenate([xyz, np.tile([1.0, 0.0, 0.0, 0.0], (T + 1, 1))], 1).astype(np.float32)
        states[i] = {"ee_pose": ee, "qpos": np.zeros((T + 1, 9), np.float32), "action": actions.astype(np.float32)}
        metas[i] = SimpleNamespace(episode_id=i, task=task, length=T, instruction="x", demo_from=0)
    ds = SimpleNamespace(episodes=list(metas.values()), meta=metas.__getitem__, load_states=states.__getitem__)
    store = SimpleNamespace(episode=lambda i: np.zeros((len(states[i]["action"]) + 1, 2, 2), np.int64))
    return ds, store


def test_a_demonstration_that_pauses_is_counted_and_one_that_moves_is_not():
    move = np.tile([0.5, 0.0, 0.0, 0, 0, 0, 1.0], (40, 1))
    pause = move.copy()
    pause[12:12 + 4 * (REST_STEPS + 1), :3] = REST_ACTION * 0.1  # REST_STEPS + 1 policy steps of (almost) nothing
    ds, store = _dataset({"a": ("push", move), "b": ("push", pause), "c": ("pull", move)})
    got = demo_rest(ds, store, ["a", "b", "c"], frame_skip=4, min_move=0.0, max_gap=12)
    assert got["push"]["episodes"] == 2 and got["push"]["rested"] == 1
    assert got["push"]["longest"] == REST_STEPS + 1 and got["push"]["rest_steps"] == REST_STEPS + 1
    assert got["pull"] == {"episodes": 1, "steps": 10, "rest_steps": 0, "rested": 0, "longest": 0}
    # re-timed, the pause is skipped over (kept frames move at least min_move) up to max_gap control steps
    retimed = demo_rest(ds, store, ["b"], frame_skip=4, min_move=0.004, max_gap=12)
    assert retimed["push"]["longest"] < REST_STEPS + 1
