"""Robot proprioception as the policy observes it, computed by ONE function from the simulator's
state in every environment (recorded episodes, the live simulator, the world model's prediction).

    proprio = [TCP position (3, decimetres, world frame), TCP orientation (6: the first two columns
               of its rotation matrix), gripper opening (1, the two finger joints summed, in cm)]

Why these parts: the TCP pose and the gripper opening are what a delta end-effector action changes,
so they are what the world model must predict next (``stages.train_wm.proprio``). The rotation as
two matrix columns is continuous (a quaternion's sign flips, and its w is ~0 for a gripper that
points down); decimetres and centimetres bring every entry to order 1 without a fitted scaler.
"""
from __future__ import annotations

import numpy as np

PROPRIO_DIM = 10
POSITION_SCALE = 10.0  # m -> dm
GRIPPER_SCALE = 100.0  # m -> cm


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) in wxyz order."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def proprio_from_state(ee_pose: np.ndarray, qpos: np.ndarray) -> np.ndarray:
    """(N, 10) float32 proprioception from TCP poses (N, 7: xyz + wxyz) and joint positions (N, 9)."""
    ee_pose, qpos = np.atleast_2d(np.asarray(ee_pose, np.float32)), np.atleast_2d(np.asarray(qpos, np.float32))
    if ee_pose.shape[-1] != 7 or qpos.shape[-1] != 9 or len(ee_pose) != len(qpos):
        raise ValueError(f"expected ee_pose (N, 7) and qpos (N, 9), got {ee_pose.shape} and {qpos.shape}")
    rot = quat_to_matrix(ee_pose[:, 3:])  # (N, 3, 3)
    return np.concatenate([
        ee_pose[:, :3] * POSITION_SCALE,
        rot[:, :, 0], rot[:, :, 1],
        (qpos[:, 7:9].sum(1, keepdims=True)) * GRIPPER_SCALE,
    ], 1).astype(np.float32)


def proprio_from_sim_state(state: np.ndarray) -> np.ndarray:
    """(N, 10) from the simulator wrapper's ``state`` (N, 16) = TCP pose (7) + qpos (9) (stages.collect.sim)."""
    state = np.atleast_2d(np.asarray(state, np.float32))
    return proprio_from_state(state[:, :7], state[:, 7:16])


def tcp_position_m(proprio: np.ndarray) -> np.ndarray:
    """TCP positions (N, 3) in metres from proprioception (N, 10)."""
    return np.asarray(proprio)[..., :3] / POSITION_SCALE
