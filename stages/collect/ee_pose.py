"""The arm controller's pose arithmetic on float32 scalars: ManiSkill's bits, without torch's per-op cost.

ManiSkill's ``pd_ee_delta_pose`` controller does its pose arithmetic as batched torch ops on a batch
of one: it reads the end effector's pose in the base frame (``inv(root) * ee``) twice per control
step and turns each action's rotation into a target quaternion (``matrix_to_quaternion`` and a
product), ~30 torch ops per quaternion product and ~0.8 ms per pose read, on a 2-core CPU about a
fifth of a simulator step (docs/collect.md, "Measured"). Here the same float32 operations run on
scalars, in the order ManiSkill's ``Pose.inv``, ``Pose.__mul__``, ``quaternion_apply``,
``matrix_to_quaternion`` and ``standardize_quaternion`` perform them, so every result is the same
float32 bit for bit: each of +, -, * and / rounds the same way in IEEE arithmetic, whatever does
it. What other libraries may round differently stays torch's: the square roots of
``matrix_to_quaternion`` (torch's float32 sqrt and numpy's differ by an ulp on some inputs) and the
rotation matrix (``euler_angles_to_matrix``: sin, cos and a matrix product). tests/collect/test_ee_pose.py checks
both against ManiSkill's on random inputs and on a live env.

``speed_up(agent)`` gives a CPU-simulated single env's arm controller this arithmetic; anything
else (a batch of envs, the GPU simulator, another controller) keeps ManiSkill's.
"""
from __future__ import annotations

import numpy as np
import torch
from mani_skill.agents.controllers.pd_ee_pose import PDEEPoseController
from mani_skill.utils.geometry.rotation_conversions import euler_angles_to_matrix
from mani_skill.utils.structs import Pose

F32 = np.float32
_NEG = F32(-1)
_ONE = F32(1)
_TWO = F32(2)
_FLOOR = F32(0.1)


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


def matrix_to_quaternion(m: np.ndarray) -> tuple:
    """(3, 3) float32 rotation matrix -> (w, x, y, z) float32, as ManiSkill's ``matrix_to_quaternion``:
    the four candidates scaled by their own |component|, the best-conditioned one kept."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = (F32(v) for v in m.reshape(9))
    sums = torch.tensor((_ONE + m00 + m11 + m22, _ONE + m00 - m11 - m22, _ONE - m00 + m11 - m22, _ONE - m00 - m11 + m22))
    # torch's float32 sqrt is not always numpy's (1 ulp apart on 17 of 3,000 random rotations): torch's, as ManiSkill's
    q_abs = torch.zeros(4)
    q_abs[sums > 0] = torch.sqrt(sums[sums > 0])
    q_abs = tuple(F32(v) for v in q_abs.numpy())
    by_rijk = ((q_abs[0] * q_abs[0], m21 - m12, m02 - m20, m10 - m01),
               (m21 - m12, q_abs[1] * q_abs[1], m10 + m01, m02 + m20),
               (m02 - m20, m10 + m01, q_abs[2] * q_abs[2], m12 + m21),
               (m10 - m01, m20 + m02, m21 + m12, q_abs[3] * q_abs[3]))
    best = max(range(4), key=lambda i: q_abs[i])  # the first of equal maxima, as torch's argmax
    den = _TWO * max(q_abs[best], _FLOOR)
    q = tuple(v / den for v in by_rijk[best])
    return tuple(-v for v in q) if q[0] < 0 else q


def _raw(link) -> np.ndarray:
    """A single-env link's world pose as (7,) float32, the values ManiSkill's ``link.pose`` holds."""
    pose = link._objs[0].entity_pose
    return np.concatenate([pose.p, pose.q]).astype(np.float32, copy=False)


class ScalarEEPoseController(PDEEPoseController):
    """ManiSkill's ``pd_ee_delta_pose`` arm controller with its pose arithmetic on float32 scalars."""

    @property
    def ee_pose_at_base(self) -> Pose:
        raw = pose_at_base(_raw(self.root_link), _raw(self.ee_link))
        return Pose.create(torch.from_numpy(raw)[None].to(self.device))  # (1, 7)

    def compute_target_pose(self, prev_ee_pose_at_base: Pose, action: torch.Tensor) -> Pose:
        """The delta action (1, 6) applied to the previous pose, in the frame this project uses
        (root translation, root-aligned body rotation); other settings go to ManiSkill's."""
        if not self.config.use_delta or self.config.frame != "root_translation:root_aligned_body_rotation":
            return super().compute_target_pose(prev_ee_pose_at_base, action)
        rot = euler_angles_to_matrix(action[:, 3:6], "XYZ")[0].numpy()  # (3, 3)
        dq = matrix_to_quaternion(rot)
        prev = prev_ee_pose_at_base.raw_pose[0].numpy()  # (7,)
        q = _qmul(dq, tuple(F32(v) for v in prev[3:]))
        if q[0] < 0:
            q = tuple(-v for v in q)
        dp = action[0, 0:3].numpy()
        p = (F32(prev[0]) + F32(dp[0]), F32(prev[1]) + F32(dp[1]), F32(prev[2]) + F32(dp[2]))
        raw = np.array((*p, *q), dtype=np.float32)
        return Pose.create(torch.from_numpy(raw)[None].to(self.device))  # (1, 7)


def speed_up(agent) -> bool:
    """Swap the agent's arm controller to ``ScalarEEPoseController`` where that is exact (one env,
    CPU simulation, ManiSkill's pose controller itself); True if it did."""
    arm = getattr(agent.controller, "controllers", {}).get("arm")
    if type(arm) is not PDEEPoseController or arm.scene.gpu_sim_enabled or arm.scene.num_envs != 1:
        return False
    arm.__class__ = ScalarEEPoseController  # a subclass that adds no state: the same object, its arithmetic replaced
    return True
