"""An episode in the simulator does not depend on what the simulator ran before it.

Resetting poses and velocities in a scene that has already simulated left the physics engine's
state from the earlier episodes in place, and the same actions from the same seed went elsewhere
(6.5 cm on the scripted push below; 3 of 16 toy collect shards differed between one and two worker
processes). Every reset now rebuilds the scene (``stages.common.sim_env``, ``stages.collect.worker``);
both tests fail without it.
"""
from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.sim


def _scripted_push(sim, seed: int, steps: int = 30) -> np.ndarray:
    """Drive the TCP to the object, down onto it and sideways through it (a hard, contact-rich push);
    the object's and the TCP's trajectory, (steps, 10)."""
    sim.reset(seed=seed)
    u = sim.env.unwrapped
    traj = []
    for t in range(steps):
        obj, tcp = u.obj.pose.p[0].numpy(), u.agent.tcp.pose.p[0].numpy()  # (3,), (3,)
        target = obj + (np.array([0.0, 0.08, 0.0]) if t > 2 * steps // 3
                        else np.array([0.0, 0.0, 0.0 if t > steps // 3 else 0.05]))
        a = np.zeros(7, np.float32)
        a[:3] = np.clip((target - tcp) / 0.02, -1, 1)
        a[6] = 1.0 if t < steps // 2 else -1.0
        sim.step(a)
        traj.append(np.concatenate([u.obj.pose.p[0].numpy(), u.obj.pose.q[0].numpy(), tcp]))
    return np.array(traj)


def test_a_sim_episode_is_the_same_whatever_ran_before_it():
    from stages.collect.sim import default_catalog
    from stages.common.sim_env import SimSpec, SimTaskEnv
    from tests.rl.tiny import obs_fn, tiny_tokenizer

    scene = next(s for s in default_catalog().values() if s.split == "ind")
    sim = SimTaskEnv([SimSpec("push", scene.to_dict())], obs_fn(tiny_tokenizer()), max_steps=30, action_repeat=2)
    try:
        first = {s: _scripted_push(sim, s) for s in (0, 1, 2)}
        again = {s: _scripted_push(sim, s) for s in (2, 1, 0)}  # each now after other episodes
    finally:
        sim.close()
    for s in first:
        assert np.abs(first[s][-1, :2] - first[s][0, :2]).max() > 0.05  # the object was pushed: contact happened
        np.testing.assert_array_equal(first[s], again[s], err_msg=f"seed {s}")


def test_a_collected_episode_is_the_same_in_a_fresh_worker_and_after_others():
    from stages.collect import worker
    from stages.collect.sim import default_catalog

    scene = next(s for s in default_catalog().values() if s.split == "ind").to_dict()

    def record(episodes):
        worker._SIMS.clear()
        env, runner, state = worker._sim("pull", 64, "lowpoly", 400)
        try:
            return [worker.record_episode(env, runner, state, scene, kind, seed) for kind, seed in episodes]
        finally:
            env.close()
            worker._SIMS.clear()

    alone = record([("near_miss", 3)])[0]
    after = record([("waypoint_noise", 3), ("interpolate", 3), ("near_miss", 3)])[-1]
    np.testing.assert_array_equal(alone.action, after.action)
    np.testing.assert_array_equal(alone.third, after.third)
