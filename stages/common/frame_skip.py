"""Frame skip: one world-model step = ``k`` control steps of the simulator.

Between two 20 Hz control steps ~98% of the tokens of a 64x64 frame do not change (measured on a
63-episode subset of real collected data, docs/world_model.md), so a next-frame model minimises its loss by copying and
learns to ignore the action. Every consumer of world-model steps therefore sees the recorded
episodes subsampled to one frame every ``k`` control steps, with the ``k`` actions between two kept
frames composed into one:

* arm dims 0..5 (delta position, delta rotation, normalised): their sum divided by ``k``, so that
  repeating the composed action ``k`` times (what the simulator does with ``action_repeat = k``,
  ``stages.common.sim_env``) moves the end effector by the same total delta (exact for positions to
  first order, approximate for the small Euler-angle rotations);
* gripper dim 6 (an absolute open / close target): the last one of the block.

Kept frames are 0, k, 2k, ... and always the last frame T (so the success frame at the end of a
demonstration is kept); a shorter final block is composed the same way (its sum over ``k``).
"""
from __future__ import annotations

import numpy as np


def frame_indices(num_actions: int, k: int) -> np.ndarray:
    """Indices (int64) of the kept frames of an episode with ``num_actions`` actions (T+1 frames)."""
    if k < 1:
        raise ValueError(f"frame_skip must be >= 1, got {k}")
    idx = np.arange(0, num_actions + 1, k, dtype=np.int64)
    if idx[-1] != num_actions:
        idx = np.append(idx, num_actions)
    return idx


def compose_actions(actions: np.ndarray, k: int) -> np.ndarray:
    """(T, 7) control actions -> (ceil(T / k), 7) composed actions between consecutive kept frames."""
    actions = np.asarray(actions, dtype=np.float32)
    if actions.ndim != 2 or actions.shape[1] != 7:
        raise ValueError(f"expected (T, 7) actions, got shape {actions.shape}")
    idx = frame_indices(len(actions), k)
    out = np.empty((len(idx) - 1, 7), np.float32)
    for j, (a, b) in enumerate(zip(idx[:-1], idx[1:])):
        out[j, :6] = actions[a:b, :6].sum(0) / k
        out[j, 6] = actions[b - 1, 6]
    return out


def per_step(values: np.ndarray, num_actions: int, k: int) -> np.ndarray:
    """Values recorded after each action (T,) -> the values after each composed action (ceil(T / k),)."""
    values = np.asarray(values)
    if len(values) != num_actions:
        raise ValueError(f"expected {num_actions} per-action values, got {len(values)}")
    return values[frame_indices(num_actions, k)[1:] - 1]
