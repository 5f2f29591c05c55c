"""The training log's success curve by start step: episodes that end early (successes) must not make
the first bins look better than the policy is."""
from types import SimpleNamespace

import numpy as np

from stages.rl.training import TrainingLog, success_by_start, success_by_task, uncensored


TASKS = ("push", "pick_place")


def drive(tmp_path, n_envs=16, steps=400, seed=0):
    """A fake PPO run whose policy never changes: every episode succeeds with probability 0.5, a success
    lasts 5 steps, a failure 20; returns the log after ``steps`` vectorised steps."""
    rng = np.random.default_rng(seed)
    env = SimpleNamespace(num_envs=n_envs)
    model = SimpleNamespace(num_timesteps=0, get_env=lambda: env)
    log = TrainingLog(tmp_path, total_timesteps=steps * n_envs, snapshots=0)
    log.init_callback(model)
    success = rng.random(n_envs) < 0.5
    state = {"left": np.where(success, 5, 20), "success": success}
    log.on_training_start({"dones": np.zeros(n_envs, bool), "infos": [{}] * n_envs, "rewards": np.zeros(n_envs)}, {})
    for _ in range(steps):
        model.num_timesteps += n_envs
        state["left"] -= 1
        dones = state["left"] == 0
        infos = [{"success": bool(state["success"][i]), "terminated_by_done_head": bool(state["success"][i]),
                  "env": f"{TASKS[i % 2]}/scene_{i}"} for i in range(n_envs)]
        log.update_locals({"dones": dones, "infos": infos, "rewards": np.zeros(n_envs)})
        log.on_step()
        for i in np.nonzero(dones)[0]:
            state["success"][i] = rng.random() < 0.5
            state["left"][i] = 5 if state["success"][i] else 20
    return log


def test_success_by_start_is_flat_when_the_policy_does_not_change(tmp_path):
    log = drive(tmp_path)
    eps = log.episodes
    # by end order the first episodes to finish are the short, successful ones
    assert np.mean([e["success"] for e in eps[:16]]) > 0.6  # 0.82 on average over 30 seeds
    kept = uncensored(eps, log.unfinished_from())
    assert 0 < len(kept) < len(eps)
    assert abs(np.mean([e["success"] for e in kept]) - 0.5) < 0.07  # ~470 episodes: 3 standard errors
    bins = success_by_start(eps, log.unfinished_from(), bins=5)
    # ~90 episodes a bin: 3 standard errors (over 30 seeds the bins average 0.48-0.50)
    assert len(bins) == 5 and all(abs(b["success"] - 0.5) <= 0.16 for b in bins)
    assert all(b["interval"][0] <= b["success"] <= b["interval"][1] for b in bins)
    # each episode's start step lies before its end step
    assert all(e["start"] < e["t"] for e in eps)


def test_the_summary_and_the_written_curve_use_start_bins(tmp_path):
    log = drive(tmp_path)
    summary = log.summary()
    assert abs(summary["success_first_fifth"] - 0.5) <= 0.16 and abs(summary["success_last_fifth"] - 0.5) <= 0.16
    log.write()
    import json
    written = json.loads((tmp_path / "success_by_start.json").read_text())
    assert written["unfinished_from"] == log.unfinished_from() and written["bins"]
    assert set(written["by_task"]) == set(TASKS)


def test_every_episode_names_its_environment_and_task_and_each_task_gets_a_curve(tmp_path):
    log = drive(tmp_path)
    assert all(e["task"] == e["env"].split("/")[0] and e["task"] in TASKS for e in log.episodes)
    by_task = success_by_task(log.episodes, log.unfinished_from())
    kept = uncensored(log.episodes, log.unfinished_from())
    # the per-task spans partition the uncensored episodes of each task
    for task in TASKS:
        assert sum(b["episodes"] for b in by_task[task]) == sum(e["task"] == task for e in kept)
    assert success_by_task([{**e, "task": ""} for e in log.episodes], log.unfinished_from()) == {}
