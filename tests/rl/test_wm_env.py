"""The world-model environment behind gymnasium / stable-baselines3 interfaces."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from stable_baselines3.common.env_checker import check_env

from stages.rl.rewards import GoalDistance, WMReward
from stages.rl.wm_env import WorldModelEnv, WorldModelVecEnv
from tests.rl.tiny import frames, obs_fn, starts_for, tiny_action_wm, tiny_tokenizer


@pytest.fixture(scope="module")
def parts():
    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    goals = tok.decode(torch.as_tensor(np.stack([s.tokens for s in starts_for(tok)[:2]]).astype(np.int64)))
    return tok, wm, goals


def _vec(parts, n=3, theta_done=0.999, max_steps=5, beta=0.01, payout_gamma=None, guard=None, dtype="fp32",
         done_persist=1):
    tok, wm, (g3, gw) = parts
    reward = WMReward(GoalDistance(g3, gw), alpha=1.0, beta=beta, theta_sps=0.5, num_envs=n)
    return WorldModelVecEnv(wm, tok, obs_fn(tok), reward, starts_for(tok), num_envs=n, max_steps=max_steps,
                            theta_done=theta_done, seed=0, payout_gamma=payout_gamma, guard=guard, dtype=dtype,
                            done_persist=done_persist)


def test_gym_env_passes_sb3_check_env(parts):
    check_env(WorldModelEnv(_vec(parts, n=1)), warn=True)


def test_vec_env_steps_truncates_and_auto_resets(parts):
    env = _vec(parts, max_steps=3)
    obs = env.reset()
    assert obs["codes"].shape == (3, 6, 8, 8) and obs["instruction"].shape == (3, 384)
    assert set(np.unique(obs["codes"])) <= {-1.0, 1.0}
    for t in range(3):
        ran = [s.env for s in env.current]  # the environments these steps run in (a finished one is replaced after)
        obs, rew, dones, infos = env.step(np.zeros((3, 7), np.float32))
        assert rew.shape == (3,) and np.isfinite(rew).all()
        assert [i["env"] for i in infos] == ran and set(ran) <= {"push/scene_0", "pull/scene_1"}
    assert dones.all() and all(i["TimeLimit.truncated"] for i in infos)
    assert all("terminal_observation" in i for i in infos)
    assert (env.t == 0).all() and env.stats["truncated"] == 3


def test_done_head_terminates_episodes(parts):
    env = _vec(parts, theta_done=1e-6, max_steps=50)
    env.reset()
    _, _, dones, infos = env.step(np.zeros((3, 7), np.float32))
    assert dones.all() and all(i["terminated_by_done_head"] and not i["TimeLimit.truncated"] for i in infos)


def test_a_held_success_terminates_only_after_done_persist_steps_counted_afresh_each_episode(parts):
    env = _vec(parts, theta_done=1e-6, max_steps=50, done_persist=3)  # the head is always above theta here
    env.reset()
    ends = []
    for t in range(1, 7):
        _, _, dones, infos = env.step(np.zeros((3, 7), np.float32))
        if dones.any():
            assert dones.all() and all(i["terminated_by_done_head"] for i in infos)
            ends.append(t)
    assert ends == [3, 6] and env.stats["terminated"] == 6  # a restarted episode holds its own count
    held = _vec(parts, theta_done=0.999, max_steps=4, done_persist=2)  # never above theta: truncated as before
    held.reset()
    for _ in range(4):
        _, _, dones, infos = held.step(np.zeros((3, 7), np.float32))
    assert dones.all() and all(i["TimeLimit.truncated"] for i in infos) and held.stats["terminated"] == 0
    with pytest.raises(ValueError, match="done_persist"):
        _vec(parts, done_persist=0)


def test_a_success_is_paid_the_maximum_for_its_step_and_the_steps_left(parts):
    plain, paid = _vec(parts, theta_done=1e-6, max_steps=50), _vec(parts, theta_done=1e-6, max_steps=50, payout_gamma=0.9)
    plain.reset(), paid.reset()
    _, r_plain, _, _ = plain.step(np.zeros((3, 7), np.float32))
    _, r_paid, dones, _ = paid.step(np.zeros((3, 7), np.float32))
    assert dones.all() and np.all(r_plain <= 1.01)  # alpha + beta bounds one step
    assert np.allclose(r_paid, 1.01 * (1 - 0.9**50) / (1 - 0.9), rtol=1e-5)  # step 1 of 50: itself + 49 left


def test_the_guard_penalises_disagreement_and_vetoes_unconfirmed_successes(parts):
    from stages.rl.guard import DoneEnsemble, Guard, fit_done_ensemble

    tok, wm, _ = parts
    torch.manual_seed(0)
    ensemble = DoneEnsemble(wm.spec.dim, heads=4)  # untrained heads disagree
    rewards = {}
    for name, guard in (("off", None), ("on", Guard(ensemble, coef=1.0, theta=0.5))):
        env = _vec(parts, max_steps=50, guard=guard)
        env.reset()
        _, rewards[name], _, infos = env.step(np.zeros((3, 7), np.float32))
    assert np.all(rewards["on"] < rewards["off"])
    assert np.allclose(rewards["off"] - rewards["on"], [1.01 * i["guard_std"] for i in infos], atol=1e-5)
    never = DoneEnsemble(wm.spec.dim, heads=2)
    for head in never.heads:  # an ensemble that never confirms: the done head alone ends nothing
        torch.nn.init.zeros_(head[-1].weight), torch.nn.init.constant_(head[-1].bias, -10.0)
    env = _vec(parts, theta_done=1e-6, max_steps=50, guard=Guard(never, coef=0.0, theta=0.5))
    env.reset()
    _, _, dones, _ = env.step(np.zeros((3, 7), np.float32))
    assert not dones.any()
    h = torch.randn(40, 8)
    model, losses = fit_done_ensemble(h, h[:, 0] > 0.5, heads=3, steps=60, lr=1e-2, seed=0)
    assert losses[-1] < losses[0] and model.probs(h).shape == (3, 40)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_actions_are_rejected(parts, bad):
    env = _vec(parts)
    env.reset()
    a = np.zeros((3, 7), np.float32)
    a[1, 2] = bad
    with pytest.raises(ValueError, match=r"NaN or inf in envs \[1\]"):
        env.step(a)


def test_wrong_action_shape_is_rejected(parts):
    env = _vec(parts)
    env.reset()
    with pytest.raises(ValueError, match=r"shape \(3, 7\)"):
        env.step(np.zeros((3, 6), np.float32))


def test_actions_change_the_imagined_future(parts):
    a, b = _vec(parts, n=1), _vec(parts, n=1)
    oa, ob = a.reset(), b.reset()
    assert np.array_equal(oa["codes"], ob["codes"])
    for _ in range(3):
        oa, *_ = a.step(np.full((1, 7), 1.0, np.float32))
        ob, *_ = b.step(np.full((1, 7), -1.0, np.float32))
    assert not np.array_equal(oa["codes"], ob["codes"])


def test_a_sparse_only_reward_decodes_no_frame_and_pays_the_same(parts, monkeypatch):
    sparse, dense = _vec(parts, beta=0.0, theta_done=1e-6, max_steps=50), _vec(parts, beta=0.01, max_steps=50)
    assert not sparse.reward.needs_frames and dense.reward.needs_frames
    tok = parts[0]
    calls = []
    real = tok.decode
    monkeypatch.setattr(tok, "decode", lambda tokens: calls.append(len(tokens)) or real(tokens))
    sparse.reset()
    _, r, dones, _ = sparse.step(np.zeros((3, 7), np.float32))
    assert calls == [] and dones.all() and r.tolist() == [1.0, 1.0, 1.0]  # done head fired: alpha * 1
    dense.reset()
    dense.step(np.zeros((3, 7), np.float32))
    assert calls  # the dense term needs the decoded frames


def test_bf16_steps_give_fp32_rewards_close_to_fp32(parts):
    """bf16 autocast of the world model and its decoding: fp32 rewards and done probabilities, the same obs layout."""
    a, b = _vec(parts, dtype="fp32"), _vec(parts, dtype="bf16")
    assert (a.dtype, b.dtype) == ("fp32", "bf16")
    oa, ob = a.reset(), b.reset()
    assert np.array_equal(oa["codes"], ob["codes"])
    _, ra, _, ia = a.step(np.zeros((3, 7), np.float32))
    obs, rb, _, ib = b.step(np.zeros((3, 7), np.float32))
    assert rb.dtype == np.float32 and np.isfinite(rb).all() and obs["codes"].dtype == oa["codes"].dtype
    assert np.allclose(ra, rb, atol=0.05)  # alpha 1 x sparse + 0.01 x (1 - LPIPS): a bf16 wobble, not a new reward
    assert all(0.0 <= i["done_prob"] <= 1.0 for i in ib)
    with pytest.raises(ValueError, match="precision must be"):
        _vec(parts, dtype="fp16")


@pytest.mark.parametrize("kind", ["numpy_uint16", "torch_int64", "list"])
def test_observation_from_tokens_takes_numpy_torch_or_lists_alike(kind):
    """The imagine-and-replay check hands the world model's token tensors (on its device) straight in;
    the env hands numpy arrays: both must give the same observation."""
    tok = tiny_tokenizer()
    fn = obs_fn(tok)
    third, wrist = frames(2)
    tokens = tok.encode(third, wrist).numpy()  # (2, h, w) int64
    given = {"numpy_uint16": tokens.astype(np.uint16), "torch_int64": torch.as_tensor(tokens),
             "list": tokens.tolist()}[kind]
    ref = fn.from_tokens(tokens, np.zeros((2, 10)), ["push the cube"] * 2)
    got = fn.from_tokens(given, np.zeros((2, 10)), ["push the cube"] * 2)
    assert set(got) == set(ref)
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k])
    assert got["codes"].dtype == np.float32 and np.isin(got["codes"], [-1.0, 1.0]).all()


def test_the_decoders_timed_layout_changes_speed_not_rewards(parts, monkeypatch):
    """On a CPU the env times the decoder in both layouts (stages.common.precision.conv_layout); forced
    either way, the same steps give the same rewards and observations."""
    import copy

    from stages.common import precision

    tok, wm, (g3, gw) = parts
    envs = {}
    for layout, (default_s, channels_last_s) in {"default": (1.0, 2.0), "channels_last": (2.0, 1.0)}.items():
        own = copy.deepcopy(tok)
        dec = own.net.decoder

        def seconds(call, dec=dec, default_s=default_s, channels_last_s=channels_last_s):
            call()  # the probe decodes a batch of frames
            w = next(m.weight for m in dec.modules() if isinstance(m, torch.nn.Conv2d))
            return channels_last_s if w.is_contiguous(memory_format=torch.channels_last) and not w.is_contiguous() else default_s

        monkeypatch.setattr(precision, "_best_seconds", seconds)
        reward = WMReward(GoalDistance(g3, gw), alpha=1.0, beta=0.01, theta_sps=0.5, num_envs=3)
        envs[layout] = WorldModelVecEnv(wm, own, obs_fn(own), reward, starts_for(own), num_envs=3, max_steps=5,
                                        theta_done=0.999, seed=0)
        assert precision.layout_of(dec) == layout
    (a, b) = envs.values()
    assert np.array_equal(a.reset()["codes"], b.reset()["codes"])
    act = np.random.default_rng(0).uniform(-1, 1, (3, 7)).astype(np.float32)
    oa, ra, _, _ = a.step(act)
    ob, rb, _, _ = b.step(act)
    assert np.array_equal(oa["codes"], ob["codes"]) and np.allclose(ra, rb, atol=1e-6)


def test_a_restart_decodes_only_the_restarted_envs_and_reads_their_first_frames(parts, monkeypatch):
    """One env of three truncates: the step decodes all three frames, the restart only that env's new first
    frame, and the progress term's start features of that env become its new first frame's."""
    tok = parts[0]
    env = _vec(parts, max_steps=4)
    env.reset()
    env.step(np.zeros((3, 7), np.float32))
    env.t[:] = [3, 1, 1]  # env 0 reaches the step cap on the next step, the others do not
    calls = []
    real = tok.decode
    monkeypatch.setattr(tok, "decode", lambda tokens: calls.append(len(tokens)) or real(tokens))
    _, _, dones, infos = env.step(np.zeros((3, 7), np.float32))
    assert dones.tolist() == [True, False, False] and infos[0]["TimeLimit.truncated"]
    assert calls == [3, 1]  # the step's frames, then the restarted env's first frame only
    first = torch.as_tensor(env.current[0].tokens[None].astype(np.int64))
    want = env.reward.distance.features(*real(first))
    for got_view, want_view in zip(env.reward.start_feats, want):
        for got, w in zip(got_view, want_view):
            assert torch.allclose(got[0:1], w, atol=1e-6)


def test_a_bf16_kv_cache_rolls_out_what_the_fp32_cache_does_under_bf16_autocast(parts):
    """Under bf16 autocast the cached attention reads keys and values in bf16 either way, so a cache kept
    in bf16 (what the bf16 world-model env uses) gives the very same frames and done probabilities."""
    from stages.common.precision import autocast

    tok, wm, _ = parts
    first = torch.as_tensor(np.stack([s.tokens for s in starts_for(tok)[:2]]).astype(np.int64))
    rolls = [wm.rollout(2, seed=0, cache_dtype=dt) for dt in (torch.float32, torch.bfloat16)]
    assert rolls[1].cache.k[0].dtype == torch.bfloat16
    for roll in rolls:
        roll.reset(first)
    acts = torch.as_tensor(np.random.default_rng(1).uniform(-1, 1, (6, 2, 7)), dtype=torch.float32)
    for a in acts:  # more steps than the window: the ring buffer wraps
        with autocast("cpu", "bf16"):
            x, y = (roll.step(a) for roll in rolls)
        assert torch.equal(x.tokens, y.tokens) and torch.equal(x.done_prob, y.done_prob)
    assert _vec(parts, dtype="bf16").roll.cache.k[0].dtype == torch.bfloat16
    assert _vec(parts, dtype="fp32").roll.cache.k[0].dtype == torch.float32
