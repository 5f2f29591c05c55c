"""Environments for RL in the world model: one per (scene, task), with its instruction and the
collected episodes whose first frames are its initial states.

Shared by ``goals`` (one goal frame per environment) and ``rl`` (reset samples an environment and
one of its initial frames).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class Environment:
    env_id: str  # "<task>/<scene_id>"
    task: str
    scene_id: str
    instruction: str
    split: str  # "ind" | "ood"
    episodes: list[str] = field(default_factory=list)  # episode ids, first frames = initial states
    successful: list[str] = field(default_factory=list)  # successful demos (optimal first), for ground-truth goals


def list_environments(collect_dir: Path, tasks: list[str] | None = None) -> list[Environment]:
    """Every (task, scene) in the collect artifact, sorted by env_id; ``tasks`` filters."""
    from stages.collect.dataset import Dataset

    envs: dict[str, Environment] = {}
    for m in Dataset(collect_dir).episodes:
        if tasks is not None and m.task not in tasks:
            continue
        env_id = f"{m.task}/{m.scene_id}"
        env = envs.setdefault(env_id, Environment(env_id, m.task, m.scene_id, m.instruction, m.split))
        env.episodes.append(m.episode_id)
        if m.success:
            (env.successful.insert(0, m.episode_id) if m.kind == "optimal" else env.successful.append(m.episode_id))
    if tasks is not None:
        unknown = sorted(set(tasks) - {e.task for e in envs.values()})
        if unknown:
            raise ValueError(f"tasks {unknown} have no episodes in {collect_dir}")
    return [envs[k] for k in sorted(envs)]
