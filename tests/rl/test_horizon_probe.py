"""scripts/horizon_probe.py: the frame k steps before a demonstration's first success, and its recorded actions from there."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from horizon_probe import start_k_before  # noqa: E402


def test_start_k_before_counts_back_from_the_frame_before_success():
    starts = ["f0", "f1", "f2", "f3"]  # frames 0-3; frame 4 is the first successful one
    assert start_k_before(starts, 1) == "f3"
    assert start_k_before(starts, 4) == "f0"


def test_start_k_before_is_none_when_the_episode_is_shorter_or_k_is_not_positive():
    assert start_k_before(["f0", "f1"], 3) is None
    assert start_k_before(["f0", "f1"], 0) is None
    assert start_k_before([], 1) is None


def test_demo_actions_are_the_recorded_ones_then_the_last_repeated():
    import numpy as np
    from horizon_probe import demo_actions

    actions = np.arange(5 * 7, dtype=np.float32).reshape(5, 7)  # (T', 7)
    np.testing.assert_array_equal(demo_actions(actions, 1, 3), actions[1:4])
    padded = demo_actions(actions, 3, 4)  # two recorded, then the last one twice
    assert padded.shape == (4, 7)
    np.testing.assert_array_equal(padded[:2], actions[3:5])
    np.testing.assert_array_equal(padded[2:], actions[[4, 4]])


@pytest.mark.sim
def test_restore_puts_the_simulator_where_the_same_actions_led_from_the_same_seed():
    import numpy as np
    from horizon_probe import restore, restore_error
    from stages.collect.sim import default_catalog
    from stages.common.sim_env import SimSpec, SimTaskEnv
    from tests.rl.tiny import obs_fn, tiny_tokenizer

    scene = next(s for s in default_catalog().values() if s.split == "ind")
    spec = SimSpec("push", scene.to_dict())
    sim = SimTaskEnv([spec], obs_fn(tiny_tokenizer()), max_steps=50, action_repeat=1)
    try:
        restore(sim, spec, 7, np.zeros((0, 7), np.float32))  # the episode's reset, as collect's
        u = sim.env.unwrapped
        actions = []
        for t in range(12):  # down to the object and through it: contact
            a = np.zeros(7, np.float32)
            a[:3] = np.clip((u.obj.pose.p[0].numpy() + [0.0, 0.06 * (t > 6), 0.0] - u.agent.tcp.pose.p[0].numpy()) / 0.02, -1, 1)
            a[6] = -1.0
            sim.step(a)
            actions.append(a)
        tcp, obj = u.agent.tcp.pose.p[0].numpy().copy(), u.obj.pose.raw_pose[0].numpy().copy()
        tokens = sim.tokens.clone()
        restore(sim, spec, 7, np.stack(actions))
        assert restore_error(sim, np.concatenate([tcp, [1, 0, 0, 0]]), obj) == (0.0, 0.0)
        assert (sim.tokens == tokens).all()
        restore(sim, spec, 7, np.stack(actions[:6]))  # fewer actions: elsewhere
        assert restore_error(sim, np.concatenate([tcp, [1, 0, 0, 0]]), obj)[0] > 1.0
    finally:
        sim.close()


def test_one_step_frame_is_the_model_step_after_the_real_history():
    import numpy as np
    import torch
    from closed_loop_divergence import one_step_frame
    from tests.rl.tiny import frames, tiny_action_wm, tiny_tokenizer

    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    third, wrist = frames(4)
    tokens = tok.encode(third, wrist).numpy()  # (4, h, w): a real history of 3 steps
    actions = np.random.default_rng(0).uniform(-1, 1, (3, 7)).astype(np.float32)
    roll = wm.rollout(1)
    roll.reset(torch.as_tensor(tokens[:1]).long())
    for u in range(2):
        roll.step(torch.as_tensor(actions[u:u + 1]), next_tokens=torch.as_tensor(tokens[u + 1:u + 2]).long())
    expected = roll.step(torch.as_tensor(actions[2:3])).tokens[0].numpy()
    np.testing.assert_array_equal(one_step_frame(wm, tokens, actions, 3), expected)
    roll = wm.rollout(1)
    roll.reset(torch.as_tensor(tokens[:1]).long())
    np.testing.assert_array_equal(one_step_frame(wm, tokens, actions, 1), roll.step(torch.as_tensor(actions[:1])).tokens[0].numpy())
