"""Filtered BC's play (stages.rl.filtered_bc): what it records, and when it stops."""
import numpy as np
import pytest

from stages.rl import Config, method_of
from stages.rl.filtered_bc import joined, play, random_like
from stages.rl.training import episode_outcome


class ScriptedVecEnv:
    """``num_envs`` envs, each playing a fixed list of (length, success) episodes in a loop. The
    observation says which env, which episode of it and which step of that episode it is."""

    def __init__(self, scripts: list[list[tuple[int, bool]]]):
        self.scripts, self.num_envs = scripts, len(scripts)
        self.episode, self.step_no = [0] * self.num_envs, [0] * self.num_envs

    def _obs(self):
        return {"where": np.array([[i, self.episode[i], self.step_no[i]] for i in range(self.num_envs)], np.float32)}

    def reset(self):
        self.episode, self.step_no = [0] * self.num_envs, [0] * self.num_envs
        return self._obs()

    def step(self, actions):
        dones, infos = np.zeros(self.num_envs, bool), []
        for i in range(self.num_envs):
            length, success = self.scripts[i][self.episode[i] % len(self.scripts[i])]
            self.step_no[i] += 1
            info = {"env": f"push/scene{i}"}
            if self.step_no[i] == length:
                dones[i] = True
                info.update({"success": success, "TimeLimit.truncated": not success})
                self.episode[i], self.step_no[i] = self.episode[i] + 1, 0
            infos.append(info)
        return self._obs(), np.ones(self.num_envs), dones, infos


class EchoPolicy:
    """Acts (env, episode, step) / 100 on the first three dimensions: each action names its observation."""

    def predict(self, obs, deterministic=True):
        a = np.zeros((len(obs["where"]), 7), np.float32)
        a[:, :3] = obs["where"] / 100
        return a, None


def test_only_successful_episodes_are_recorded_each_with_its_own_steps_and_actions():
    env = ScriptedVecEnv([[(3, True), (2, False)], [(4, False), (1, True)]])
    played = play(EchoPolicy(), env, budget=12, seed=0)
    wins = [e for e in played.episodes if e["success"]]
    assert len(played.successes) == len(wins) > 0
    for (obs, actions), row in zip(played.successes, wins):
        where = obs["where"]  # (T, 3): one env, one episode, steps 0..T-1
        assert len(where) == len(actions) == row["length"]
        assert len(set(where[:, 0])) == 1 and len(set(where[:, 1])) == 1
        assert where[:, 2].tolist() == list(range(row["length"]))
        np.testing.assert_allclose(actions[:, :3], where / 100, atol=1e-6)  # the action taken at that observation
    assert not any(obs["where"][0, 2] != 0 for obs, _ in played.successes)
    failures = [e for e in played.episodes if not e["success"]]
    assert failures and all(not e["terminated"] for e in failures)


def test_the_budget_ends_play_but_every_episode_it_started_is_played_to_its_end():
    env = ScriptedVecEnv([[(5, True)], [(3, False)]])
    played = play(EchoPolicy(), env, budget=8, seed=0, step0=100)
    # steps are counted over both envs: the budget is reached after 4 vector steps; env 0's second episode began
    # before it (at 100 + 10) and runs to its end, every episode that began after it is left out
    assert played.budget_reached_at == 108 and all(e["start"] < 108 for e in played.episodes)
    assert [(e["env"], e["start"], e["t"], e["length"]) for e in played.episodes] == [
        ("push/scene1", 100, 106, 3), ("push/scene0", 100, 110, 5), ("push/scene1", 106, 112, 3)]
    assert played.steps == 12 and len(played.successes) == 1


def test_world_model_episodes_succeed_when_the_done_head_ends_them():
    assert episode_outcome({"terminated_by_done_head": True, "TimeLimit.truncated": False}) == (True, True)
    assert episode_outcome({"terminated_by_done_head": False, "TimeLimit.truncated": True}) == (False, False)
    assert episode_outcome({"success": False, "TimeLimit.truncated": True}) == (False, False)
    assert episode_outcome({"success": True}) == (True, True)


def test_own_episodes_follow_the_demonstrations():
    demos = ({"x": np.zeros((2, 3), np.float32)}, np.zeros((2, 7), np.float32))
    own = [({"x": np.ones((3, 3), np.float64)}, np.ones((3, 7), np.float32))]
    obs, actions = joined(demos, own)
    assert obs["x"].dtype == np.float32 and obs["x"].shape == (5, 3) and actions[2:].tolist() == [[1.0] * 7] * 3
    assert joined(demos, [])[1] is demos[1]


def test_filtered_bc_is_named_and_checked_by_its_config():
    assert method_of("rule", "success", "filtered_bc") == "rule_fbc" and method_of("wm", "success", "filtered_bc") == "wm_fbc"
    assert method_of("rule", "dense") == "rule_dense"
    assert method_of("wm", "success", calibration_ratio=0.5) == "wm_gated"
    assert method_of("wm", "success", calibration_ratio=0.5, imagined_bc_epochs=20) == "wm_gated_ibc"
    assert method_of("wm", "success", branch_horizon=10, imagined_bc_epochs=20) == "wm_branched_ibc"
    assert method_of("wm", "success", "filtered_bc", "random") == "wm_fbc_random"
    assert method_of("rule", "success", "filtered_bc", "none") == "rule_fbc_none"
    assert method_of("wm", "success", "filtered_bc", done_persist=3) == "wm_fbc_persist"
    assert method_of("wm", "success", calibration_ratio=0.5, imagined_bc_epochs=20, done_persist=2) == "wm_gated_ibc_persist"
    with pytest.raises(ValueError, match="leave it at 1"):
        Config(algorithm="filtered_bc", reward="rule", done_persist=2)
    with pytest.raises(ValueError, match="none would end as a success"):
        Config(algorithm="filtered_bc", reward="wm", done_persist=16, max_episode_steps=15)
    assert Config(algorithm="filtered_bc", reward="wm", done_persist=15, max_episode_steps=15).done_persist == 15
    for select in ("random", "none"):
        with pytest.raises(ValueError, match="set rl.algorithm=filtered_bc"):
            Config(algorithm="ppo", fbc_select=select)
    with pytest.raises(ValueError, match="use reward rule or wm"):
        Config(algorithm="filtered_bc", reward="proxy")
    with pytest.raises(ValueError, match="plays every training environment"):
        Config(algorithm="filtered_bc", reward="wm", calibration_ratio=0.5)
    with pytest.raises(ValueError, match="runs no PPO"):
        Config(algorithm="filtered_bc", reward="wm", guard=True, guard_replay_rounds=1)


def test_failures_are_kept_only_when_asked_and_play_is_the_same_either_way():
    scripts = [[(3, True), (2, False)], [(4, False), (1, True)]]
    plain = play(EchoPolicy(), ScriptedVecEnv(scripts), budget=12, seed=0)
    both = play(EchoPolicy(), ScriptedVecEnv(scripts), budget=12, seed=0, keep_failures=True)
    assert plain.failures == [] and plain.episodes == [{**e, "wall": p["wall"]} for e, p in zip(both.episodes, plain.episodes)]
    assert len(both.failures) == sum(not e["success"] for e in both.episodes) > 0
    assert [len(a) for _, a in both.failures] == [e["length"] for e in both.episodes if not e["success"]]
    assert all(len(set(o["where"][:, 1])) == 1 for o, _ in both.failures)  # each one episode's steps


def test_the_random_control_imitates_as_many_steps_as_the_successes_have_whatever_their_outcome():
    env = ScriptedVecEnv([[(2, True), (6, False)], [(6, False), (2, True)], [(6, False)]])
    played = play(EchoPolicy(), env, budget=60, seed=0, keep_failures=True)
    target = sum(len(a) for _, a in played.successes)
    assert target > 0 and played.failures
    seen_failure = False
    for seed in range(20):
        picked = random_like(played, np.random.default_rng(seed))
        steps = sum(len(a) for _, a in picked)
        assert target <= steps < target + 6  # stops once it holds the successes' steps; the last may pass them
        assert steps - len(picked[-1][1]) < target
        seen_failure |= any(any(p is f for f in played.failures) for p in picked)
    assert seen_failure  # failures are drawn too: the outcome plays no part
    first = random_like(played, np.random.default_rng(3))
    assert [id(p) for p in first] == [id(p) for p in random_like(played, np.random.default_rng(3))]
    assert random_like(play(EchoPolicy(), ScriptedVecEnv([[(3, False)]]), budget=9, seed=0, keep_failures=True),
                       np.random.default_rng(0)) == []  # no success: nothing to match, nothing imitated
