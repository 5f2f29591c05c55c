"""Demonstrations as (observation, action) pairs at the policy's step (``frame_skip`` control steps).

Re-timing (``min_move``): the planner's trajectories are time-parametrised, so every motion segment
starts from rest with a slow ramp (composed actions 0.00, 0.01, 0.10, 0.24, ... of the normalised
range) and ends with a slow one. A policy that sees one frame cannot tell the start of a segment
from its end, and at a rest point the demonstrations say "move by ~0": cloned, it stalls there.
With ``min_move > 0`` the next kept frame after frame t is the first one at least ``frame_skip``
control steps later whose TCP has moved ``min_move`` metres (at most ``max_gap`` control steps
later, never across a change of the gripper command), and the action is the sum of the control
actions in between divided by ``frame_skip``: repeated ``frame_skip`` times, as every environment
executes a policy step, it moves the arm as far as the demonstration did. Rest phases (the gripper
closing) keep their zero arm action; what disappears is the near-zero first step of each motion.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.frame_skip import compose_actions, frame_indices
from stages.common.proprio import proprio_from_state


@dataclass
class Demo:
    """One demonstration at policy steps: frame tokens (T'+1, h, w), proprio (T'+1, 10), actions (T', 7)."""

    episode_id: str
    instruction: str
    tokens: np.ndarray
    proprio: np.ndarray
    actions: np.ndarray
    obj_xyz: np.ndarray | None = None  # (T'+1, 3) object centre (m), when the shard records it
    first: np.ndarray | None = None  # (h, w) the episode's first frame's tokens when that is not tokens[0] (a DAgger continuation)


def retimed_indices(tcp_xyz: np.ndarray, gripper: np.ndarray, frame_skip: int, min_move: float, max_gap: int) -> np.ndarray:
    """Kept control frames (int64, from 0 to T) under the re-timing rule of the module docstring.

    tcp_xyz (T+1, 3) metres, gripper (T,) the gripper command of each control action.
    """
    n_actions = len(gripper)
    idx, t = [0], 0
    while t < n_actions:
        n = min(t + frame_skip, n_actions)
        while (n < min(t + max_gap, n_actions) and np.linalg.norm(tcp_xyz[n] - tcp_xyz[t]) < min_move
               and gripper[n] == gripper[n - 1]):
            n += 1
        idx.append(n)
        t = n
    return np.asarray(idx, dtype=np.int64)


def compose_between(actions: np.ndarray, idx: np.ndarray, frame_skip: int) -> np.ndarray:
    """(len(idx) - 1, 7): arm dims summed between kept frames / ``frame_skip`` (clipped to [-1, 1]), gripper the last."""
    out = np.empty((len(idx) - 1, 7), np.float32)
    for j, (a, b) in enumerate(zip(idx[:-1], idx[1:])):
        out[j, :6] = np.clip(actions[a:b, :6].sum(0) / frame_skip, -1.0, 1.0)
        out[j, 6] = actions[b - 1, 6]
    return out


def load_demo(ds, store, episode_id: str, frame_skip: int, min_move: float = 0.0, max_gap: int = 12) -> Demo:
    """The episode's kept frames with their proprioception and composed actions: every ``frame_skip``-th
    (``stages.common.frame_skip``), or re-timed when ``min_move > 0`` (module docstring), from its
    ``demo_from`` control step on (a recovery episode's deliberate mistake is left out)."""
    meta = ds.meta(episode_id)
    states = ds.load_states(episode_id)
    tokens = np.asarray(store.episode(episode_id), dtype=np.int64)
    if len(tokens) != meta.length + 1:
        raise ValueError(f"episode {episode_id}: {len(tokens)} token frames, collect says {meta.length + 1}")
    s = meta.demo_from  # a recovery episode's mistake (its first s actions) is never imitated
    if min_move > 0:
        idx = s + retimed_indices(states["ee_pose"][s:, :3], states["action"][s:, 6], frame_skip, min_move, max_gap)
        actions = compose_between(states["action"], idx, frame_skip)
    else:
        idx = s + frame_indices(meta.length - s, frame_skip)
        actions = compose_actions(states["action"][s:], frame_skip)
    obj = states["obj_pose"][idx, :3] if "obj_pose" in states else None
    return Demo(episode_id, meta.instruction, tokens[idx], proprio_from_state(states["ee_pose"][idx], states["qpos"][idx]),
                actions, obj)


def pairs(demos: list[Demo], obs_fn) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Observation batch and actions (M, 7) of every (frame, next action) of ``demos``."""
    parts, acts = [], []
    for d in demos:
        n = len(d.actions)
        first = d.tokens[:1] if d.first is None else np.asarray(d.first)[None]  # (1, h, w)
        parts.append(obs_fn.from_tokens(d.tokens[:n], d.proprio[:n], [d.instruction] * n,
                                        first=np.repeat(first, n, axis=0)))
        acts.append(d.actions)
    if not parts:
        raise ValueError("no demonstration pairs")
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}, np.concatenate(acts).astype(np.float32)
