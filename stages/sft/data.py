"""Demonstrations as (observation, action) pairs at the policy's step (``frame_skip`` control steps)."""
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


def load_demo(ds, store, episode_id: str, frame_skip: int) -> Demo:
    """The episode's kept frames (``stages.common.frame_skip``) with their proprioception and composed actions."""
    meta = ds.meta(episode_id)
    states = ds.load_states(episode_id)
    idx = frame_indices(meta.length, frame_skip)
    tokens = np.asarray(store.episode(episode_id), dtype=np.int64)
    if len(tokens) != meta.length + 1:
        raise ValueError(f"episode {episode_id}: {len(tokens)} token frames, collect says {meta.length + 1}")
    obj = states["obj_pose"][idx, :3] if "obj_pose" in states else None
    return Demo(episode_id, meta.instruction, tokens[idx], proprio_from_state(states["ee_pose"][idx], states["qpos"][idx]),
                compose_actions(states["action"], frame_skip), obj)


def pairs(demos: list[Demo], obs_fn) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Observation batch and actions (M, 7) of every (frame, next action) of ``demos``."""
    parts, acts = [], []
    for d in demos:
        n = len(d.actions)
        parts.append(obs_fn.from_tokens(d.tokens[:n], d.proprio[:n], [d.instruction] * n))
        acts.append(d.actions)
    if not parts:
        raise ValueError("no demonstration pairs")
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}, np.concatenate(acts).astype(np.float32)
