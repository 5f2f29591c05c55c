"""Run a policy in the simulator: the work unit ``ctx.map`` fans out (one sim env per job, reused)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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


def run_job(job: Job) -> list[dict]:
    """One result dict per seed: success (the task's own check at any step), steps, optional frames."""
    import torch

    from stages.rl import load_policy
    from stages.rl.observation import ObservationFn
    from stages.rl.policy import act
    from stages.rl.sim_env import SimSpec, SimTaskEnv
    from stages.tokenize.tokenizer import load_tokenizer

    torch.set_num_threads(1)
    tok = load_tokenizer(job.tokenize_dir, job.device)
    obs_fn = ObservationFn(tok, job.text_embeddings)
    model = load_policy(job.policy_path, job.device)
    spec = SimSpec(job.task, job.scene)
    env = SimTaskEnv([spec], obs_fn, max_steps=job.max_steps, image_size=job.image_size, robot_mesh=job.robot_mesh,
                     action_repeat=job.action_repeat)
    out = []
    try:
        for seed in job.seeds:
            env.keep_frames = seed in job.record
            obs, info = env.reset(seed=seed, options={"spec": spec})
            success, steps = bool(info["success"]), 0
            while not success and steps < job.max_steps:
                obs, _, terminated, truncated, info = env.step(act(model, {k: v[None] for k, v in obs.items()})[0])
                steps += 1
                success = success or bool(info["success"])
                if terminated or truncated:
                    break
            res = {"policy": job.policy, "task": job.task, "scene_id": job.scene["scene_id"], "split": job.split,
                   "seed": seed, "success": success, "steps": steps, "instruction": env.instruction}
            if env.keep_frames:
                res["frames"] = np.stack([f[0] for f in env.frames])  # (control steps+1, H, W, 3) third view
            out.append(res)
    finally:
        env.close()
    return out
