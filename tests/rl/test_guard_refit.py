"""The guard's refit on replayed imagined episodes: labels from replays, the callback's schedule."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.rl.guard import Guard
from stages.rl.guard_refit import GuardRefit, replay_labels
from stages.rl.imagined import replay_row


def test_replay_labels_mark_the_first_real_success_and_every_step_before_it_negative():
    hidden = torch.arange(2 * 5 * 3, dtype=torch.float32).view(2, 5, 3)  # (N, T, D)
    rows = [replay_row("a", np.array([0.1, 0.9, 0.9, 0.9, 0.9]), 3, 0.5),  # imagined done at 2, real at 3
            replay_row("b", np.array([0.1, 0.2, 0.95, 0.9, 0.9]), -1, 0.5)]  # imagined done, never real
    x, y = replay_labels(rows, hidden)
    assert x.shape == (3 + 5, 3) and y.tolist() == [False, False, True] + [False] * 5
    assert torch.equal(x[2], hidden[0, 2]) and torch.equal(x[3:], hidden[1])
    with pytest.raises(ValueError, match="2 replay rows but hidden states of 1"):
        replay_labels(rows, hidden[:1])


class _Env:
    guard = None


def test_the_callback_refits_at_evenly_spaced_steps_and_replaces_the_guard():
    torch.manual_seed(0)
    base_h = torch.randn(60, 4)
    base_s = base_h[:, 0] > 0.8
    calls = []

    def imagine(policy, k):
        calls.append(k)
        h = torch.randn(2, 6, 4)
        return [replay_row("a", np.full(6, 0.9), 2, 0.5), replay_row("b", np.full(6, 0.9), -1, 0.5)], h

    env = _Env()
    cb = GuardRefit(env, imagine, base_h, base_s, total_timesteps=300, rounds=2, heads=2, steps=5, lr=1e-2,
                    seed=0, coef=1.0, theta=0.5)
    cb.model = type("M", (), {"policy": None})()
    for n in (64, 128, 192, 256, 300):  # rollout ends; refits are due at 100 and 200 steps
        cb.num_timesteps = n
        cb._on_rollout_end()
    assert calls == [0, 1] and isinstance(env.guard, Guard)
    m = cb.metrics()
    assert m["guard/replay/rounds_done"] == 2 and m["guard/replay/round1/timesteps"] == 128
    assert m["guard/replay/round2/timesteps"] == 256
    assert m["guard/replay/frames"] == 2 * (2 + 6) and m["guard/replay/positive_frames"] == 2
    assert m["guard/replay/round1/imagined_done"] == 2 and m["guard/replay/round1/imagined_and_replayed"] == 0
    assert m["guard/replay/sim_policy_steps"] == 2 * (2 + 6)


def test_guard_replay_needs_the_guard():
    from stages.rl import Config

    with pytest.raises(ValueError, match="set rl.guard=true"):
        Config(guard_replay_rounds=1)
    assert Config(guard=True, guard_replay_rounds=1).guard_replay_envs == 64


def test_replay_imagined_loads_the_guard_an_rl_artifact_saved(tmp_path):
    import sys
    from pathlib import Path

    from stages.rl.guard import DoneEnsemble

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
    from replay_imagined import load_guard

    torch.manual_seed(0)
    saved = DoneEnsemble(12, 3).eval()
    torch.save(saved.state_dict(), tmp_path / "guard.pt")  # what the rl stage writes
    guard = load_guard(tmp_path / "guard.pt", theta=0.5)
    h = torch.randn(7, 12)
    assert torch.allclose(guard.ensemble.probs(h), saved.probs(h))
    assert guard(h)[1].tolist() == (saved.probs(h).mean(0) >= 0.5).tolist()
    with pytest.raises(SystemExit, match="rl.guard=true"):
        load_guard(tmp_path / "missing.pt", theta=0.5)


def test_replay_imagined_prints_imagined_beside_replayed_gripper_opening(capsys):
    import sys
    from pathlib import Path

    import numpy as np

    from stages.rl.imagined import Replay

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
    from replay_imagined import print_gripper

    proprio = np.zeros((2, 8, 10), np.float32)  # (N, T, 10) imagined, the opening last
    proprio[0, :, -1] = [8, 6, 4, 4, 4, 4, 4, 4]  # closes on an imagined object
    proprio[1, :, -1] = [8, 6, 2, 1, 0.5, 0.5, 0.5, 0.5]
    replayed = [[np.full(10, v, np.float32) for v in (8, 4, 0, 0)], [np.full(10, 8, np.float32)] * 8]
    rows = [Replay("pick_place/a", done_at=4, success=False), Replay("push/b", done_at=-1, success=False)]
    print_gripper(rows, {"proprio": proprio, "replay_proprio": replayed}, every=2)
    out = capsys.readouterr().out.splitlines()
    assert "FALSE" in out[1] and "min imagined 4.0, min replayed 0.0: 6.0/4.0 4.0/0.0" in out[1]
    assert "no imagined done" in out[2] and "min imagined 0.5, min replayed 8.0" in out[2]
    assert out[2].count("/8.0") == 4  # every 2nd of 8 steps to the end without a done
