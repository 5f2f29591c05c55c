"""The policy sees the same kind of input in the world model and in the simulator."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.rl.rewards import GoalDistance, WMReward
from stages.rl.wm_env import Start, WorldModelVecEnv
from tests.rl.tiny import obs_fn, tiny_action_wm, tiny_tokenizer

pytestmark = pytest.mark.sim


def test_wm_env_and_sim_env_observe_a_real_frame_identically():
    from stages.collect.sim import default_catalog
    from stages.common.sim_env import SimSpec, SimTaskEnv

    tok = tiny_tokenizer()
    fn = obs_fn(tok)
    scene = next(s for s in default_catalog().values() if s.split == "ind")
    sim = SimTaskEnv([SimSpec("push", scene.to_dict())], fn, max_steps=3, keep_frames=True)
    try:
        obs_sim, _ = sim.reset(seed=0)
        third, wrist = sim.frames[0]
        assert third.shape == (64, 64, 3) and third.dtype == np.uint8 and third.std() > 5  # a real rendered frame
        tokens = tok.encode(third[None], wrist[None]).numpy()[0]
        wm = tiny_action_wm(tok)
        goal = tok.decode(torch.as_tensor(tokens[None]))
        vec = WorldModelVecEnv(wm, tok, fn, WMReward(GoalDistance(*goal), alpha=1, beta=0.01, theta_sps=0.5),
                               [Start(0, sim.instruction, tokens, obs_sim["proprio"])], num_envs=1, max_steps=3,
                               theta_done=0.99)
        obs_wm = vec.reset()
        assert set(obs_wm) == set(obs_sim) == {"codes", "proprio", "instruction"}
        for k in obs_sim:
            np.testing.assert_array_equal(obs_wm[k][0], obs_sim[k])
        # the real robot state went through stages.common.proprio: TCP ~above the table, fingers open
        state = sim.env._obs(sim.env.unwrapped.get_obs(unflattened=True))["state"]
        np.testing.assert_allclose(obs_sim["proprio"][:3], state[:3] * 10, rtol=1e-6)
        assert 7.0 < obs_sim["proprio"][9] < 8.5  # gripper opening in cm
        obs_sim2, *_ = sim.step(np.zeros(7, np.float32))
        obs_wm2, *_ = vec.step(np.zeros((1, 7), np.float32))
        for k in obs_sim:
            assert obs_sim2[k].shape == obs_wm2[k][0].shape
    finally:
        sim.close()


def test_a_sim_step_repeats_the_action_for_the_world_models_frame_skip():
    from stages.collect.sim import default_catalog
    from stages.common.sim_env import SimSpec, SimTaskEnv

    tok = tiny_tokenizer()
    scene = next(s for s in default_catalog().values() if s.split == "ind")
    sim = SimTaskEnv([SimSpec("push", scene.to_dict())], obs_fn(tok), max_steps=2, keep_frames=True, action_repeat=3)
    try:
        sim.reset(seed=0)
        up = np.zeros(7, np.float32)
        up[2] = 1.0  # +z, gripper target 0
        _, _, term, trunc, _ = sim.step(up)
        assert len(sim.frames) == 1 + 3  # the reset frame + one per control step
        assert not term and not trunc
        _, _, term, trunc, _ = sim.step(up)
        assert trunc and len(sim.frames) == 1 + 6  # max_steps counts policy steps
        assert not np.array_equal(sim.frames[0][1], sim.frames[-1][1])  # the wrist camera moved
    finally:
        sim.close()
    with pytest.raises(ValueError, match="action_repeat"):
        SimTaskEnv([SimSpec("push", scene.to_dict())], obs_fn(tok), max_steps=2, action_repeat=0)


def test_unrendered_repeats_reach_the_same_state_as_rendered_ones():
    """The first k-1 control steps of a policy step skip the cameras; the result equals k full steps."""
    from stages.collect.sim import default_catalog
    from stages.common.sim_env import SimSpec, SimTaskEnv

    tok = tiny_tokenizer()
    scene = next(s for s in default_catalog().values() if s.split == "ind")
    spec = SimSpec("push", scene.to_dict())
    full = SimTaskEnv([spec], obs_fn(tok), max_steps=5, keep_frames=True, action_repeat=4)  # renders every step
    fast = SimTaskEnv([spec], obs_fn(tok), max_steps=5, action_repeat=4)
    try:
        full.reset(seed=3)
        obs, _ = fast.reset(seed=3)
        reset_frame = full.frames[0]
        raw, reward, truncated, info = fast._observe_current(np.zeros(7, np.float32))  # no step: same picture
        np.testing.assert_array_equal(raw["third"], reset_frame[0])
        np.testing.assert_array_equal(raw["wrist"], reset_frame[1])
        assert np.isfinite(reward) and not truncated and info["success"] is False
        rng = np.random.default_rng(0)
        for _ in range(3):
            a = rng.uniform(-1, 1, 7).astype(np.float32)
            o_full, r_full, t_full, *_ = full.step(a)
            o_fast, r_fast, t_fast, *_ = fast.step(a)
            np.testing.assert_array_equal(o_full["codes"], o_fast["codes"])
            assert r_full == pytest.approx(r_fast, abs=1e-6) and t_full == t_fast
            q_full = full.env.unwrapped.agent.robot.get_qpos().numpy()
            q_fast = fast.env.unwrapped.agent.robot.get_qpos().numpy()
            np.testing.assert_allclose(q_full, q_fast, atol=1e-6)
        assert int(fast.env.unwrapped.elapsed_steps.reshape(-1)[0]) == 12  # every control step counted
        assert len(full.frames) == 1 + 12
    finally:
        full.close()
        fast.close()


def test_sim_env_keeps_the_episode_first_frame_where_the_policy_reads_it():
    """``sft.frame=both``: the second half of the codes is the first frame's, step after step, and a
    new episode brings its own first frame."""
    from stages.collect.sim import default_catalog
    from stages.common.sim_env import SimSpec, SimTaskEnv
    from stages.sft.observation import ObservationFn
    from tests.rl.tiny import text_embeddings

    tok = tiny_tokenizer()
    scene = next(s for s in default_catalog().values() if s.split == "ind")
    fn = ObservationFn(tok, text_embeddings([]), "both")
    sim = SimTaskEnv([SimSpec("push", scene.to_dict())], fn, max_steps=3, keep_frames=True)
    try:
        obs0, _ = sim.reset(seed=0)
        third, wrist = sim.frames[0]
        first = tok.codes(tok.encode(third[None], wrist[None]))[0].numpy()  # (bits, h, w)
        np.testing.assert_array_equal(obs0["codes"][: tok.bits], first)
        np.testing.assert_array_equal(obs0["codes"][tok.bits:], first)
        down = np.zeros(7, np.float32)
        down[2] = -1.0
        for _ in range(2):
            obs, *_ = sim.step(down)
            now = tok.codes(tok.encode(*(f[None] for f in sim.frames[-1])))[0].numpy()
            np.testing.assert_array_equal(obs["codes"][: tok.bits], now)
            np.testing.assert_array_equal(obs["codes"][tok.bits:], first)
        assert not np.array_equal(now, first)  # the arm moved: the two halves differ now
        obs1, _ = sim.reset(seed=1)
        np.testing.assert_array_equal(obs1["codes"][tok.bits:], obs1["codes"][: tok.bits])
    finally:
        sim.close()


def test_a_simulator_built_after_the_last_one_closed_renders_the_same_pixels_with_the_held_renderer():
    """``keep_renderer``: closing the last env no longer frees SAPIEN's renderer (its BRDF table is not
    regenerated for the next env), and what the next env renders is what the first one did."""
    from stages.collect.sim import default_catalog
    from stages.common import sim_env
    from stages.common.sim_env import SimSpec, SimTaskEnv

    tok = tiny_tokenizer()
    scene = next(s for s in default_catalog().values() if s.split == "ind")
    frames = []
    for _ in range(2):
        sim = SimTaskEnv([SimSpec("pick_place", scene.to_dict())], obs_fn(tok), max_steps=2, keep_frames=True)
        try:
            sim.reset(seed=5)
            sim.step(np.array([0.5, -0.5, 0.5, 0, 0, 0, -1], np.float32))
            device = str(sim.env.unwrapped.backend.render_device)
            frames.append([f.copy() for pair in sim.frames for f in pair])
        finally:
            sim.close()
        assert device in sim_env._KEPT_RENDERERS  # held past the close
    import gc

    assert sim_env._FROZEN and gc.get_freeze_count() > 0  # the heap alive before the first simulator is frozen
    assert len(frames[0]) == len(frames[1]) == 4
    for a, b in zip(*frames):
        np.testing.assert_array_equal(a, b)
