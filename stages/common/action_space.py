"""The 7-d action as a policy emits it and as every environment executes it.

Dims 0..5 are the normalised delta end-effector pose (``stages.collect.actions``), clipped to
[-1, 1]. Dim 6 is the gripper, and the demonstrations only ever command +1 (open) or -1 (closed):
a policy's continuous output there is a decision, executed by its sign (>= 0 opens). Executing the
sign in the simulator AND in the world model keeps the two environments the same MDP, and a
Gaussian policy's noise on dim 6 then flips the decision rather than half-closing the hand.
"""
from __future__ import annotations

import numpy as np

GRIPPER = 6


def executed(actions: np.ndarray) -> np.ndarray:
    """(..., 7) float32: arm dims clipped to [-1, 1], the gripper dim replaced by +-1 (its sign, 0 -> +1)."""
    a = np.clip(np.asarray(actions, dtype=np.float32), -1.0, 1.0).copy()
    a[..., GRIPPER] = np.where(a[..., GRIPPER] >= 0, 1.0, -1.0)
    return a
