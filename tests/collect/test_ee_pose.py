"""The controller's pose arithmetic on scalars (stages/collect/ee_pose.py) equals ManiSkill's torch one bit for bit."""
import numpy as np
import pytest
import torch

from stages.collect.envs import DEFAULT_SCENE  # noqa: F401  (sets up Vulkan, then imports sapien)
from stages.collect import ee_pose  # noqa: E402
from mani_skill.agents.controllers.pd_ee_pose import PDEEPoseController  # noqa: E402
from mani_skill.utils.geometry.rotation_conversions import euler_angles_to_matrix, matrix_to_quaternion  # noqa: E402
from mani_skill.utils.structs import Pose  # noqa: E402


def _random_poses(rng, n: int) -> np.ndarray:
    """(n, 7) float32 poses: positions in [-1, 1], unit quaternions of both signs of w."""
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([rng.uniform(-1, 1, (n, 3)), q], axis=1).astype(np.float32)


def test_pose_at_base_equals_maniskills_products_bitwise():
    rng = np.random.default_rng(0)
    roots, ees = _random_poses(rng, 2000), _random_poses(rng, 2000)
    for root, ee in zip(roots, ees):
        expected = (Pose.create(torch.from_numpy(root)).inv() * Pose.create(torch.from_numpy(ee))).raw_pose[0]
        got = ee_pose.pose_at_base(root, ee)
        assert got.dtype == np.float32
        assert np.array_equal(got.view(np.int32), expected.numpy().view(np.int32)), (root, ee, got, expected)


def _bits(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float32).view(np.int32)


def test_matrix_to_quaternion_equals_maniskills_bitwise():
    rng = np.random.default_rng(2)
    angles = np.concatenate([
        rng.uniform(-np.pi, np.pi, (3000, 3)),                      # any rotation
        rng.uniform(-0.1, 0.1, (1000, 3)),                          # small ones, as the controller's deltas
        rng.choice([0.0, np.pi / 2, -np.pi / 2, np.pi, -np.pi], (200, 3)),  # where candidates tie
    ]).astype(np.float32)
    mats = euler_angles_to_matrix(torch.from_numpy(angles), "XYZ")  # (N, 3, 3)
    for m in mats:  # one at a time, as the controller converts them
        expected = matrix_to_quaternion(m[None])[0].numpy()
        assert np.array_equal(_bits(ee_pose.matrix_to_quaternion(m.numpy())), _bits(expected)), (m, expected)


@pytest.mark.sim
def test_live_env_uses_it_and_steps_exactly_as_without(monkeypatch):
    from stages.collect.sim import make_task_env

    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, (40, 7)).astype(np.float32)

    def rollout(env) -> list[np.ndarray]:
        states = []
        for seed in (0, 1):  # the second reset rebuilds the scene, and with it the controller
            env.reset(seed=seed)
            arm = env.unwrapped.agent.controller.controllers["arm"]
            for a in actions[:20]:
                env.step(a)
                states.append(env.unwrapped.agent.robot.get_qpos().numpy().copy())
                if type(arm) is ee_pose.ScalarEEPoseController:  # the replaced arithmetic against ManiSkill's own
                    ours, theirs = arm.ee_pose_at_base.raw_pose, PDEEPoseController.ee_pose_at_base.fget(arm).raw_pose
                    assert ours.dtype == theirs.dtype and ours.shape == theirs.shape == (1, 7)
                    assert torch.equal(ours, theirs)
                    delta = torch.from_numpy(rng.uniform(-0.1, 0.1, (1, 6)).astype(np.float32))
                    prev = arm.ee_pose_at_base
                    ours = arm.compute_target_pose(prev, delta).raw_pose
                    theirs = PDEEPoseController.compute_target_pose(arm, prev, delta).raw_pose
                    assert ours.dtype == theirs.dtype and ours.shape == theirs.shape == (1, 7)
                    assert torch.equal(ours, theirs)
        return states

    fast_env = make_task_env("pick_place", DEFAULT_SCENE)
    fast = rollout(fast_env)
    assert type(fast_env.unwrapped.agent.controller.controllers["arm"]) is ee_pose.ScalarEEPoseController
    fast_env.close()

    monkeypatch.setattr(ee_pose, "speed_up", lambda agent: False)
    slow_env = make_task_env("pick_place", DEFAULT_SCENE)
    slow = rollout(slow_env)
    assert type(slow_env.unwrapped.agent.controller.controllers["arm"]) is PDEEPoseController
    slow_env.close()
    assert all(np.array_equal(a, b) for a, b in zip(fast, slow)) and len(fast) == len(slow) == 40
