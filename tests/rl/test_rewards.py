"""Reward modules: sign of the dense reward, when the sparse reward fires, return scales."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from stages.rl import Config
from stages.rl.rewards import REGISTRY, GoalDistance, RewardParts, StepBatch, WMReward, success_return
from stages.rl.success_only import SuccessOnly
from tests.rl.tiny import frames


def _to_t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(x).permute(0, 3, 1, 2).float() / 255


@pytest.fixture(scope="module")
def scene():
    third, wrist = frames(2, seed=3)
    start = (_to_t(third[:1]), _to_t(wrist[:1]))
    goal = (_to_t(third[1:]), _to_t(wrist[1:]))
    return start, goal


def _batch(third, wrist, done, goal_index):
    n = third.shape[0]
    return StepBatch(torch.zeros(n, 1, 1, dtype=torch.long), torch.as_tensor(done, dtype=torch.float32),
                     torch.zeros(n, 4), np.asarray(goal_index), third, wrist)


def _towards_goal(scene, n: int):
    """Frames (n, 3, H, W) per view, interpolated from the start to the goal."""
    (s3, sw), (g3, gw) = scene
    ks = torch.linspace(0, 1, n)[:, None, None, None]
    return (1 - ks) * s3 + ks * g3, (1 - ks) * sw + ks * gw


def test_dense_reward_rises_as_the_frame_approaches_the_goal(scene):
    (_, _), (g3, gw) = scene
    reward = WMReward(GoalDistance(g3, gw), alpha=0.0, beta=1.0, theta_sps=0.5, dense="similarity", num_envs=6)
    third, wrist = _towards_goal(scene, 6)
    r = reward(_batch(third, wrist, np.zeros(6), np.zeros(6, dtype=int)))
    assert np.all(np.diff(r) > 0), r  # similarity, not distance: closer is better
    assert r[-1] == pytest.approx(1.0, abs=1e-5) and r[0] < 0.9


def test_progress_rises_from_minus_to_plus_the_start_goal_distance(scene):
    (s3, sw), (g3, gw) = scene
    dist = GoalDistance(g3, gw)
    reward = WMReward(dist, alpha=0.0, beta=1.0, theta_sps=0.5, dense="progress", num_envs=6)
    third, wrist = _towards_goal(scene, 6)
    starts = _batch(s3.repeat(6, 1, 1, 1), sw.repeat(6, 1, 1, 1), np.zeros(6), np.zeros(6, dtype=int))
    reward.reset(np.arange(6), starts)
    r = reward(_batch(third, wrist, np.zeros(6), np.zeros(6, dtype=int)))
    span = dist(s3, sw, [0])[0]  # LPIPS(start, goal)
    assert np.all(np.diff(r) > 0), r
    assert r[0] == pytest.approx(-span, abs=1e-5) and r[-1] == pytest.approx(span, abs=1e-5)


def test_progress_reads_each_envs_own_first_frame_across_restarts(scene):
    (s3, sw), (g3, gw) = scene
    reward = WMReward(GoalDistance(g3, gw), alpha=0.0, beta=1.0, theta_sps=0.5, dense="progress", num_envs=2)
    with pytest.raises(RuntimeError, match="reset"):
        reward(_batch(s3.repeat(2, 1, 1, 1), sw.repeat(2, 1, 1, 1), np.zeros(2), [0, 0]))
    reward.reset(np.arange(2), _batch(s3.repeat(2, 1, 1, 1), sw.repeat(2, 1, 1, 1), np.zeros(2), [0, 0]))
    at_goal = _batch(g3.repeat(2, 1, 1, 1), gw.repeat(2, 1, 1, 1), np.zeros(2), [0, 0])
    before = reward(at_goal)
    # env 1 restarts at the goal itself: it has come nowhere; env 0 keeps its start
    reward.reset(np.array([1]), _batch(g3, gw, np.zeros(1), [0]))
    after = reward(at_goal)
    assert after[0] == pytest.approx(before[0]) and before[1] > 0.05
    assert after[1] == pytest.approx(0.0, abs=1e-6)


def test_sparse_reward_fires_exactly_at_theta(scene):
    (s3, sw), (g3, gw) = scene
    reward = WMReward(GoalDistance(g3, gw), alpha=1.0, beta=0.0, theta_sps=0.5, num_envs=4)
    done = np.array([0.0, 0.4999, 0.5, 0.93])
    r = reward(_batch(s3.repeat(4, 1, 1, 1), sw.repeat(4, 1, 1, 1), done, np.zeros(4, dtype=int)))
    assert r.tolist() == [0.0, 0.0, 1.0, 1.0]


def test_potential_shaping_telescopes(scene):
    (s3, sw), (g3, gw) = scene
    dist = GoalDistance(g3, gw)
    reward = WMReward(dist, alpha=0.0, beta=1.0, theta_sps=0.5, dense="potential", gamma=1.0, num_envs=1)
    path = [(1 - k) * s3 + k * g3 for k in (0.0, 0.3, 0.2, 0.7, 1.0)]
    wpath = [(1 - k) * sw + k * gw for k in (0.0, 0.3, 0.2, 0.7, 1.0)]
    reward.reset(np.array([0]), _batch(path[0], wpath[0], [0.0], [0]))
    total = sum(float(reward(_batch(p, w, [0.0], [0]))[0]) for p, w in zip(path[1:], wpath[1:]))
    phi0, phi_t = -dist(path[0], wpath[0], [0])[0], -dist(path[-1], wpath[-1], [0])[0]
    assert total == pytest.approx(phi_t - phi0, abs=1e-5)  # the detour (0.3 -> 0.2) earns nothing overall


def test_goal_index_selects_each_envs_goal(scene):
    (s3, sw), (g3, gw) = scene
    dist = GoalDistance(torch.cat([s3, g3]), torch.cat([sw, gw]))
    d = dist(torch.cat([s3, s3]), torch.cat([sw, sw]), np.array([0, 1]))
    assert d[0] == pytest.approx(0.0, abs=1e-6) and d[1] > 0.05


def test_return_scales_are_checked():
    with pytest.raises(ValueError, match="linger"):
        Config(alpha=0.5, beta=0.02, max_episode_steps=50, success_payout=False)
    Config(alpha=0.5, beta=0.02, max_episode_steps=50, dense="potential", success_payout=False)  # shaping cannot be farmed
    Config(alpha=2.0, beta=0.02, max_episode_steps=50, success_payout=False)
    Config(alpha=0.5, beta=0.02, max_episode_steps=50)  # the success payout makes finishing worth the most
    for reward in ("rule", "embedding", "proxy"):  # their per-step reward is positive next to the goal
        with pytest.raises(ValueError, match="linger"):
            Config(reward=reward, rule_terms="dense", success_payout=False)
    Config(reward="rule", rule_terms="success", success_payout=False)  # success alone: lingering earns 0


def test_success_return_is_the_maximum_for_this_step_and_every_step_left():
    assert success_return(2.0, 0, 0.9) == pytest.approx(2.0)
    assert success_return(2.0, 2, 0.9) == pytest.approx(2.0 * (1 + 0.9 + 0.81))
    assert success_return(1.0, 3, 1.0) == pytest.approx(4.0)
    assert np.allclose(success_return(1.0, np.array([0, 1]), 0.5), [1.0, 1.5])


def test_unknown_reward_module_is_refused():
    with pytest.raises(ValueError, match="reward"):
        Config(reward="lpips")


@pytest.mark.parametrize("dense", ["progress", "similarity", "potential"])
def test_diagnostics_along_an_episode_equal_the_env_stepping_the_module(scene, dense):
    """Diagnostics score episodes with ``along``; the env calls the module step by step: same rewards."""
    (s3, sw), (g3, gw) = scene
    t = torch.linspace(0, 1, 5)[:, None, None, None]
    third, wrist = (1 - t) * s3 + t * g3, (1 - t) * sw + t * gw  # (5, 3, H, W): start -> goal
    done = np.array([0.0, 0.2, 0.4, 0.7, 0.9])
    make = lambda: WMReward(GoalDistance(g3, gw), alpha=1.0, beta=0.5, theta_sps=0.5, dense=dense, gamma=0.9)  # noqa: E731
    first, frames = _batch(third[:1], wrist[:1], done[:1], [0]), _batch(third[1:], wrist[1:], done[1:], [0] * 4)
    stepped = make()
    stepped.reset(np.array([0]), first)
    one_by_one = [stepped(_batch(third[i:i + 1], wrist[i:i + 1], done[i:i + 1], [0]))[0] for i in range(1, 5)]
    assert np.allclose(make().along(first, frames), one_by_one)


def test_every_registered_module_builds_from_the_rl_config(scene):
    from stages.rl.rewards import EmbeddingHead, ProxyCNN

    (_, _), (g3, gw) = scene
    parts = RewardParts(GoalDistance(g3, gw), {"embedding": EmbeddingHead(4), "proxy": ProxyCNN()})
    for name, cls in REGISTRY.items():
        module = cls.build(parts, Config(reward=name), num_envs=2)
        assert module.name == name and module.max_step_reward > 0
        assert cls.needs_head is None or cls.needs_head in parts.heads


def test_bf16_lpips_stays_close_to_fp32_and_leaves_the_shared_network_alone(scene):
    from stages.common.lpips import get_lpips

    (s3, sw), (g3, gw) = scene
    ks = torch.linspace(0, 1, 5)[:, None, None, None]
    third, wrist = (1 - ks) * s3 + ks * g3, (1 - ks) * sw + ks * gw  # (5, 3, H, W) from start to goal
    fp32 = GoalDistance(g3, gw, dtype="fp32")(third, wrist, np.zeros(5, dtype=int))
    low = GoalDistance(g3, gw, dtype="bf16")
    bf16 = low(third, wrist, np.zeros(5, dtype=int))
    assert low.net is not get_lpips("cpu") and get_lpips("cpu").convs[0].weight.is_contiguous()
    assert np.abs(bf16 - fp32).max() < 0.02, (fp32, bf16)
    assert np.all(np.diff(bf16) < 0)  # the order along the path survives


class _Scripted(gym.Env):
    """Pays 0.7 per step (the dense reward next to the goal), succeeds at the third step with 5."""

    observation_space = gym.spaces.Box(-1, 1, (1,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        self.t += 1
        success = self.t == 3
        return np.zeros(1, np.float32), (5.0 if success else 0.7), success, False, {"success": success}


def test_success_only_rule_pays_the_successful_step_and_nothing_else():
    env = SuccessOnly(_Scripted())
    env.reset()
    rewards = [env.step(np.zeros(1, np.float32))[1] for _ in range(3)]
    assert rewards == [0.0, 0.0, 5.0]
    cfg = Config(reward="rule", rule_terms="success")
    recorded = np.array([0.3, 0.8, 1.0])  # normalised dense reward of an episode: 1 exactly at success
    batch = StepBatch(torch.zeros(3, 1, 1, dtype=torch.long), torch.zeros(3), torch.zeros(3, 4),
                      np.zeros(3, dtype=int), rule_reward=recorded)
    assert REGISTRY["rule"].build(RewardParts(), cfg, 3)(batch).tolist() == [0.0, 0.0, 1.0]  # diagnostics as trained
    assert REGISTRY["rule"].build(RewardParts(), Config(reward="rule", rule_terms="dense"), 3)(batch).tolist() == recorded.tolist()
