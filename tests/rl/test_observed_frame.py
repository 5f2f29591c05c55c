"""``sft.frame``: which frame's tokens the policy reads, the same in the world model, the demonstrations
and the simulator (stages/sft/observation.py)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.rl.rewards import GoalDistance, WMReward
from stages.rl.wm_env import WorldModelVecEnv
from stages.sft.data import Demo, pairs
from stages.sft.observation import ObservationFn
from tests.rl.tiny import frames, starts_for, text_embeddings, tiny_action_wm, tiny_tokenizer

TEXT = text_embeddings(["push the cube", "pull the cube"])


@pytest.fixture(scope="module")
def tok():
    return tiny_tokenizer()


def _tokens(tok, n: int, seed: int) -> np.ndarray:
    third, wrist = frames(n, seed=seed)
    return tok.encode(third, wrist).numpy()  # (n, h, w)


def test_each_mode_reads_its_frame(tok):
    now, first = _tokens(tok, 2, seed=1), _tokens(tok, 2, seed=2)
    assert not np.array_equal(now, first)
    proprio, instr = np.zeros((2, 10)), ["push the cube"] * 2
    codes = {m: ObservationFn(tok, TEXT, m).from_tokens(now, proprio, instr, first=first)["codes"]
             for m in ("current", "first", "both")}
    now_codes, first_codes = tok.codes(now).numpy(), tok.codes(first).numpy()
    np.testing.assert_array_equal(codes["current"], now_codes)
    np.testing.assert_array_equal(codes["first"], first_codes)
    np.testing.assert_array_equal(codes["both"], np.concatenate([now_codes, first_codes], axis=1))
    for m, c in codes.items():
        assert ObservationFn(tok, TEXT, m).space["codes"].shape == c.shape[1:]
    assert codes["both"].shape[1] == 2 * tok.bits


def test_a_mode_that_needs_the_first_frame_says_so(tok):
    now = _tokens(tok, 1, seed=1)
    with pytest.raises(ValueError, match="first-frame tokens"):
        ObservationFn(tok, TEXT, "first").from_tokens(now, np.zeros((1, 10)), ["push the cube"])
    with pytest.raises(ValueError, match="unknown observed frame 'last'"):
        ObservationFn(tok, TEXT, "last")
    # without a first frame the current mode is what it always was
    ObservationFn(tok, TEXT).from_tokens(now, np.zeros((1, 10)), ["push the cube"])


def test_policy_json_without_a_frame_is_the_current_frame(tok):
    assert ObservationFn.for_policy(tok, TEXT, {"observation": ["codes"]}).frame == "current"
    assert ObservationFn.for_policy(tok, TEXT, {"frame": "first"}).frame == "first"


@pytest.mark.parametrize("mode", ["first", "both"])
def test_world_model_env_shows_each_env_its_own_start(tok, mode):
    """Across steps and auto-resets, the first-frame part of every env's observation is its start's."""
    wm = tiny_action_wm(tok)
    starts = starts_for(tok)
    goals = tok.decode(torch.as_tensor(np.stack([s.tokens for s in starts[:2]]).astype(np.int64)))
    reward = WMReward(GoalDistance(*goals), alpha=1.0, beta=0.01, theta_sps=0.5, num_envs=3)
    env = WorldModelVecEnv(wm, tok, ObservationFn(tok, TEXT, mode), reward, starts, num_envs=3, max_steps=2,
                           theta_done=0.999, seed=0)
    obs = env.reset()
    bits = tok.bits
    for _ in range(5):  # crosses two truncations, so rows restart from newly drawn starts
        want = tok.codes(np.stack([s.tokens for s in env.current])).numpy()  # (3, bits, h, w)
        np.testing.assert_array_equal(obs["codes"][:, -bits:], want)
        obs, _, _, _ = env.step(np.zeros((3, 7), np.float32))
    assert obs["codes"].shape[1] == bits * (2 if mode == "both" else 1)


def test_demonstration_pairs_pair_every_step_with_the_episode_start(tok):
    t = _tokens(tok, 4, seed=3)
    demo = Demo("e0", "push the cube", t, np.zeros((4, 10), np.float32), np.zeros((3, 7), np.float32))
    obs, actions = pairs([demo], ObservationFn(tok, TEXT, "first"))
    assert len(actions) == 3
    np.testing.assert_array_equal(obs["codes"], np.repeat(tok.codes(t[:1]).numpy(), 3, axis=0))
    obs, _ = pairs([demo], ObservationFn(tok, TEXT, "current"))
    np.testing.assert_array_equal(obs["codes"], tok.codes(t[:3]).numpy())
