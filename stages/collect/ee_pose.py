"""The arm controller's end-effector pose in the robot's base frame, without torch's per-op cost.

ManiSkill's ``pd_ee_delta_pose`` controller reads ``ee_pose_at_base`` (``inv(root) * ee``) twice per
control step, as batched torch quaternion products on a batch of one pose: ~30 torch ops per
product, ~0.8 ms per read, and on a 2-core CPU about a fifth of a simulator step (docs/collect.md,
"Measured"). Here the same products run on float32 scalars, operation for operation in the order
ManiSkill's ``Pose.inv``, ``Pose.__mul__``, ``quaternion_apply`` and ``standardize_quaternion``
perform them, so every result is the same float32 bit for bit (each IEEE operation rounds the same
way; tests/collect/test_ee_pose.py checks it against ManiSkill's on random poses and on a live env).

``speed_up(agent)`` gives a CPU-simulated single env's arm controller this computation; anything
else (a batch of envs, the GPU simulator, another controller) keeps ManiSkill's.
"""
from __future__ import annotations

import numpy as np
import torch
from mani_skill.agents.controllers.pd_ee_pose import PDEEPoseController
from mani_skill.utils.structs import Pose

F32 = np.float32
_NEG = F32(-1)
_ONE = F32(1)


def _qmul(a: tuple, b: tuple) -> tuple:
    """Hamilton product of two (w, x, y, z) float32 quaternions, as ``quaternion_raw_multiply``."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def _rotate(q: tuple, p: tuple) -> tuple:
    """``q`` applied to the point ``p``, as ``quaternion_apply``: q * (0, p) * q^-1 (the inverse by a
    multiplication with (1, -1, -1, -1), as ``quaternion_invert``)."""
    conj = (q[0] * _ONE, q[1] * _NEG, q[2] * _NEG, q[3] * _NEG)
    return _qmul(_qmul(q, (F32(0), *p)), conj)[1:]


def pose_at_base(root: np.ndarray, ee: np.ndarray) -> np.ndarray:
    """``inv(root) * ee`` for two (7,) float32 poses (xyz, then quaternion wxyz) -> (7,) float32."""
    rp, rq = tuple(F32(v) for v in root[:3]), tuple(F32(v) for v in root[3:])
    ep, eq = tuple(F32(v) for v in ee[:3]), tuple(F32(v) for v in ee[3:])
    iq = (rq[0], -rq[1], -rq[2], -rq[3])                       # Pose.inv: the conjugate ...
    ip = _rotate(iq, tuple(-v for v in rp))                    # ... and the rotated, negated position
    q = _qmul(iq, eq)                                          # Pose.__mul__: quaternion_multiply ...
    if q[0] < 0:                                               # ... standardized: real part >= 0
        q = tuple(-v for v in q)
    rot = _rotate(iq, ep)
    return np.array((ip[0] + rot[0], ip[1] + rot[1], ip[2] + rot[2], *q), dtype=np.float32)


def _raw(link) -> np.ndarray:
    """A single-env link's world pose as (7,) float32, the values ManiSkill's ``link.pose`` holds."""
    pose = link._objs[0].entity_pose
    return np.concatenate([pose.p, pose.q]).astype(np.float32, copy=False)


class ScalarEEPoseController(PDEEPoseController):
    """ManiSkill's ``pd_ee_delta_pose`` arm controller with ``ee_pose_at_base`` on float32 scalars."""

    @property
    def ee_pose_at_base(self) -> Pose:
        raw = pose_at_base(_raw(self.root_link), _raw(self.ee_link))
        return Pose.create(torch.from_numpy(raw)[None].to(self.device))  # (1, 7)


def speed_up(agent) -> bool:
    """Swap the agent's arm controller to ``ScalarEEPoseController`` where that is exact (one env,
    CPU simulation, ManiSkill's pose controller itself); True if it did."""
    arm = getattr(agent.controller, "controllers", {}).get("arm")
    if type(arm) is not PDEEPoseController or arm.scene.gpu_sim_enabled or arm.scene.num_envs != 1:
        return False
    arm.__class__ = ScalarEEPoseController  # a subclass that adds no state: the same object, one property replaced
    return True
