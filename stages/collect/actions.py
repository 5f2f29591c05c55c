"""The 7-d delta end-effector action, exactly as ManiSkill's ``pd_ee_delta_pose`` controller reads it.

ManiSkill 3.0.1's ``PDEEPoseController`` (frame ``root_translation:root_aligned_body_rotation``,
``use_target=False``, normalized actions) turns an action ``a`` into a target TCP pose in the
robot-base frame, relative to the *current* TCP pose ``(p, q)``:

    p_target = p + pos_scale * clip(a[0:3], -1, 1)          pos_scale = 0.1 m
    r        = a[3:6] / max(1, |a[3:6]|)
    q_target = quat(euler_XYZ(rot_scale * r)) * q           rot_scale = rot_lower = -0.1 rad
    gripper  = a[6]: +1 open (finger target 0.04 m), -1 closed (-0.01 m)

(``rot_scale`` is the controller config's ``rot_lower``, negative in 3.0.1: the sign is the
controller's, and it is read from the live controller so the inverse below stays exact.)
``delta_ee_action`` inverts this: given current and target TCP poses it returns the action that
makes the controller aim at the target (clipped when a step exceeds 0.1 m or 0.1 rad).
"""
from __future__ import annotations

from stages.common.vulkan import ensure_vulkan

ensure_vulkan()  # before sapien is imported

import numpy as np
import torch

from mani_skill.utils.geometry.rotation_conversions import matrix_to_euler_angles, quaternion_to_matrix

GRIPPER_OPEN, GRIPPER_CLOSED = 1.0, -1.0


def controller_scales(env) -> tuple[float, float]:
    """(pos_scale, rot_scale) of the env's ``pd_ee_delta_pose`` arm controller."""
    cfg = env.unwrapped.agent.controller.controllers["arm"].config
    if not cfg.normalize_action or not cfg.use_delta or cfg.use_target:
        raise ValueError("expected a normalized, delta, non-target pd_ee_delta_pose arm controller")
    if cfg.frame != "root_translation:root_aligned_body_rotation":
        raise ValueError(f"unsupported controller frame {cfg.frame!r}")
    pos_hi = float(np.broadcast_to(cfg.pos_upper, 3)[0])
    return pos_hi, float(np.broadcast_to(cfg.rot_lower, 3)[0])


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])


def _quat_inv(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]]) / np.dot(q, q)


def delta_ee_action(cur: np.ndarray, target: np.ndarray, gripper: float, pos_scale: float, rot_scale: float) -> np.ndarray:
    """The (7,) float32 normalized action moving the TCP from ``cur`` to ``target``.

    ``cur`` / ``target``: (7,) TCP poses in the robot-base frame, xyz + quaternion wxyz.
    """
    dpos = (target[:3] - cur[:3]) / pos_scale
    dq = _quat_mul(target[3:], _quat_inv(cur[3:]))
    if dq[0] < 0:  # same rotation, shortest way round
        dq = -dq
    euler = matrix_to_euler_angles(quaternion_to_matrix(torch.as_tensor(dq, dtype=torch.float64)), "XYZ").numpy()
    rot = euler / rot_scale
    norm = np.linalg.norm(rot)
    if norm > 1:
        rot = rot / norm
    return np.concatenate([np.clip(dpos, -1, 1), rot, [gripper]]).astype(np.float32)
