"""scripts/dense_view_probe.py: which view the dense term's correlation with progress comes from."""
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from dense_view_probe import episode_distances, relative, view_correlations  # noqa: E402


def test_view_correlations_read_each_view_apart():
    t = np.arange(10, dtype=np.float64)
    d = {"third": np.full(10, 0.3), "wrist": 1.0 - t / 10}  # the wrist view nears its goal, the third view is still
    d["both"] = (d["third"] + d["wrist"]) / 2
    d["start"] = np.full(10, 0.2)
    r = view_correlations(d)
    assert np.isnan(r["third"]) and r["wrist"] == pytest.approx(1.0) and r["both"] == pytest.approx(1.0)
    assert np.isnan(r["w0"]) and r["w1"] == pytest.approx(1.0)
    d["third"] = t / 10  # now the third view moves away from its goal, as fast as the wrist view nears its own
    d["both"] = (d["third"] + d["wrist"]) / 2
    r = view_correlations(d)
    assert r["third"] == pytest.approx(-1.0) and np.isnan(r["both"])
    assert r["w0.75"] == pytest.approx(1.0) and r["w0.25"] == pytest.approx(-1.0)


def test_start_relative_terms_read_the_distance_to_the_start_too():
    t = np.arange(1, 11, dtype=np.float64) / 10
    d = {"both": np.full(10, 0.4), "start": t}  # the goal no nearer, the frame ever further from the start
    terms = relative(d)
    assert np.allclose(terms["diff"], t - 0.4) and np.allclose(terms["ratio"], t / (t + 0.4))
    r = view_correlations({**d, "third": d["both"], "wrist": d["both"]})
    assert np.isnan(r["both"])  # the goal term alone sees nothing
    assert r["diff"] == pytest.approx(1.0) and r["ratio"] == pytest.approx(1.0) and r["start"] == pytest.approx(1.0)
    d["start"] = t[::-1].copy()  # back towards the start: the relative terms fall
    assert view_correlations({**d, "third": d["both"], "wrist": d["both"]})["diff"] == pytest.approx(-1.0)


def test_episode_distances_compare_each_view_with_its_own_goal():
    from stages.rl.rewards import GoalDistance

    g = torch.Generator().manual_seed(0)
    goal_third, goal_wrist = torch.rand(2, 3, 32, 32, generator=g), torch.rand(2, 3, 32, 32, generator=g)
    steps = torch.linspace(1, 0, 6)[:, None, None, None]  # frames 1..5 walk from noise to goal row 1 (T = 5)
    noise = torch.rand(6, 3, 32, 32, generator=g)
    third = steps * noise + (1 - steps) * goal_third[1]
    wrist = goal_wrist[1].expand(6, -1, -1, -1)  # already at its goal throughout
    inp = SimpleNamespace(tokens=lambda eid: np.zeros((6, 2, 2), np.int64), env_of=lambda eid: 1,
                          tok=SimpleNamespace(decode=lambda tokens: (third[-len(tokens):], wrist[-len(tokens):])))
    dist = GoalDistance(goal_third, goal_wrist)
    d = episode_distances(inp, dist, "e")
    assert all(len(v) == 5 for v in d.values())
    assert d["third"][0] > 0.01 and d["third"][-1] < 1e-4  # from noise to its goal
    assert np.all(d["wrist"] < 1e-4)  # compared with goal_wrist[1], not goal_third[1]
    assert np.allclose(d["both"], (d["third"] + d["wrist"]) / 2)
    with torch.no_grad():  # to frame 0: the third view's LPIPS (the wrist view never moved), halved by the views' mean
        to_first = dist.net(third[1:] * 2 - 1, third[:1].expand(5, -1, -1, -1) * 2 - 1).numpy()
    assert np.allclose(d["start"], to_first / 2, atol=1e-5) and np.all(d["start"] > 0.01)
