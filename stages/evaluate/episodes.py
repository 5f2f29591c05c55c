"""Run policies in the simulator: ``run_group`` (one scene's jobs) is the work unit ``ctx.map`` fans out."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.common.rest import REST_ACTION, REST_STEPS, longest_rest  # noqa: F401  (the report reads them from here)


@dataclass
class Job:
    """Episodes of one policy in one (task, scene); plain data so it pickles to workers / Ray."""

    policy: str  # label, e.g. "sft", "ppo", "ppo@step_00001000"
    policy_path: str
    tokenize_dir: str
    text_embeddings: dict
    task: str
    scene: dict
    split: str  # "ind" | "ood" | "extra"
    seeds: list[int]
    max_steps: int  # policy steps
    action_repeat: int = 1  # control steps per policy step (the world model's frame skip)
    image_size: int = 64
    robot_mesh: str = "lowpoly"
    record: list[int] = field(default_factory=list)  # seeds whose third-view frames are returned
    device: str = "cpu"
    frame: str = "current"  # which frame's tokens the policy reads (sft.frame, its policy.json)


_SIMS: dict = {}  # per worker process: (tokenizer, text, camera, repeat, horizon) -> SimTaskEnv, reused across jobs


def _sim_for(job: Job):
    """The worker's simulator env for ``job``, built once per process and kept open between jobs.

    Why kept: closing a process's last SAPIEN env released its renderer, and the next env's first
    pictures then cost ~12 s (measured 11-14 s inside SAPIEN's take_picture for a new env vs 0.2 s
    while another env is alive), which made one-episode jobs ~4x their episode time. The renderer is
    now held for the process's life (``stages.common.sim_env.keep_renderer``); keeping the env also
    keeps its tokenizer and scene loaded between jobs. ``close_sims`` ends them.
    """
    import hashlib
    import json

    import torch

    from stages.common.sim_env import SimTaskEnv
    from stages.sft.observation import ObservationFn
    from stages.tokenize.tokenizer import load_tokenizer

    text_id = hashlib.blake2b(json.dumps(job.text_embeddings, sort_keys=True).encode(), digest_size=8).hexdigest()
    key = (job.tokenize_dir, text_id, job.image_size, job.robot_mesh, job.action_repeat, job.max_steps, job.device, job.frame)
    if key not in _SIMS:
        close_sims()
        torch.set_num_threads(1)
        obs_fn = ObservationFn(load_tokenizer(job.tokenize_dir, job.device), job.text_embeddings, job.frame)
        _SIMS[key] = SimTaskEnv([_spec(job)], obs_fn, max_steps=job.max_steps, image_size=job.image_size,
                                robot_mesh=job.robot_mesh, action_repeat=job.action_repeat)
    return _SIMS[key]


def _spec(job: Job):
    from stages.common.sim_env import SimSpec

    return SimSpec(job.task, job.scene)


def close_sims() -> None:
    """Close this process's cached simulator envs (and forget its loaded policies)."""
    while _SIMS:
        _SIMS.popitem()[1].close()
    _POLICIES.clear()


_POLICIES: dict = {}  # per worker process: (policy path, mtime, size, device) -> the loaded policy, reused across jobs


def _policy_for(job: Job):
    """The job's policy, loaded once per process: a policy is read-only in evaluation, and a scene's
    jobs (``jobs.environment_groups``) alternate between the policies (0.19 s a load, measured)."""
    from stages.sft.policy import load_policy

    stat = Path(job.policy_path).stat()
    key = (job.policy_path, stat.st_mtime_ns, stat.st_size, job.device)  # a file rewritten in place is read again
    if key not in _POLICIES:
        _POLICIES[key] = load_policy(job.policy_path, job.device)
    return _POLICIES[key]


def run_group(jobs: list[Job]) -> list[list[dict]]:
    """``run_job`` of each job in order: the jobs of one (task, scene) (``jobs.environment_groups``)."""
    return [run_job(job) for job in jobs]


def run_job(job: Job) -> list[dict]:
    """One result dict per seed: success (the task's own check at any step), steps, the longest run of
    steps the policy commanded rest (``longest_rest``), optional frames."""
    from stages.sft.policy import act

    env = _sim_for(job)
    model = _policy_for(job)
    spec = _spec(job)
    out = []
    try:
        for seed in job.seeds:
            env.keep_frames = seed in job.record
            obs, info = env.reset(seed=seed, options={"spec": spec})
            success, steps, moves = bool(info["success"]), 0, []
            while not success and steps < job.max_steps:
                action = act(model, {k: v[None] for k, v in obs.items()})[0]  # (7,)
                moves.append(action[:3])
                obs, _, terminated, truncated, info = env.step(action)
                steps += 1
                success = success or bool(info["success"])
                if terminated or truncated:
                    break
            res = {"policy": job.policy, "task": job.task, "scene_id": job.scene["scene_id"], "split": job.split,
                   "seed": seed, "success": success, "steps": steps, "instruction": env.instruction,
                   "rest_steps": longest_rest(np.asarray(moves))}
            if env.keep_frames:
                res["frames"] = np.stack([f[0] for f in env.frames])  # (control steps+1, H, W, 3) third view
            out.append(res)
    finally:
        env.keep_frames = False
    return out
