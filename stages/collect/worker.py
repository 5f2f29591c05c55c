"""One collection shard: plan, execute, record and write its episodes (runs in a worker process).

Each worker process keeps one simulator per (task, image size, robot mesh) and reuses it across
episodes and shards (the first camera env costs 6-12 s; a scene change is a cheap reconfigure).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from stages.collect import plans
from stages.collect.mcap_io import ShardWriter

_SIMS: dict = {}  # (task, image_size, robot_mesh) -> (env, PlanRunner), per worker process
RETRY_SEED_STRIDE = 1_000_003


def _sim(task: str, image_size: int, robot_mesh: str, max_steps: int):
    from stages.collect.execute import PlanRunner
    from stages.collect.sim import make_raw_env

    key = (task, image_size, robot_mesh)
    if key not in _SIMS:
        from stages.collect.envs import DEFAULT_SCENE

        env = make_raw_env(task, DEFAULT_SCENE, image_size=image_size, robot_mesh=robot_mesh,
                           reconfiguration_freq=1)  # each reset rebuilds the scene: episodes do not depend on earlier ones
        _SIMS[key] = (env, PlanRunner(env, max_steps), {"scene_id": None})
    env, runner, state = _SIMS[key]
    runner.max_steps = max_steps
    return env, runner, state


def record_episode(env, runner, state: dict, scene: dict, kind: str, seed: int):
    """Reset to (scene, seed), build the ``kind`` plan and execute it. Raises PlanFailure."""
    from stages.collect.execute import layout_from_env

    options = None
    if state["scene_id"] != scene["scene_id"]:
        options = dict(reconfigure=True, scene=scene)
        state["scene_id"] = None  # stays unknown if the reset fails
    obs, info = env.reset(seed=seed, options=options)
    state["scene_id"] = scene["scene_id"]
    rng = np.random.default_rng([seed, plans.KINDS.index(kind)])
    plan = plans.suboptimal_plan(plans.optimal_plan(layout_from_env(env)), kind, rng)
    return runner.run(plan, obs, info)


def collect_shard(job: dict) -> dict:
    """Collect ``job["episodes"]`` into ``job["path"]``; returns episode metas and counters.

    job keys: path, task, image_size, robot_mesh, max_steps, max_retries, keep_failed,
    episodes: [{episode_id, scene, kind, seed, replay}].
    """
    from stages.collect.execute import PlanFailure, replay

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    env, runner, state = _sim(job["task"], job["image_size"], job["robot_mesh"], job["max_steps"])
    stats = dict(attempts=0, plan_failures=0, exec_failures=0, unintended_successes=0, retries=0, dropped=0, written=0, frames=0,
                 replayed=0, replay_success=0, replay_exact=0, replay_seconds=0.0)
    metas = []
    writer = ShardWriter(Path(job["path"]))
    try:
        for ep in job["episodes"]:
            rec, seed = None, None
            for attempt in range(job["max_retries"] + 1):
                seed = ep["seed"] + attempt * RETRY_SEED_STRIDE
                stats["attempts"] += 1
                stats["retries"] += attempt > 0
                try:
                    rec = record_episode(env, runner, state, ep["scene"], ep["kind"], seed)
                except PlanFailure:
                    stats["plan_failures"] += 1
                    rec = None
                    continue
                if ep["kind"] in plans.FAILURE_KINDS:  # a negative must not succeed at any frame
                    if not rec.success.any():
                        break
                    stats["unintended_successes"] += 1
                elif rec.success[-1] or job["keep_failed"]:
                    break
                else:
                    stats["exec_failures"] += 1
                rec = None
            if rec is None:
                stats["dropped"] += 1
                continue
            if ep["replay"] and rec.success[-1]:
                t_replay = time.perf_counter()
                replayed = replay(env, seed, rec.action)
                stats["replay_seconds"] += time.perf_counter() - t_replay
                stats["replayed"] += 1
                stats["replay_success"] += bool(replayed[-1])
                stats["replay_exact"] += bool(np.array_equal(replayed, rec.success))
            scene = ep["scene"]
            meta = dict(
                episode_id=ep["episode_id"], task=job["task"], instruction=env.unwrapped.instruction,
                scene_id=scene["scene_id"], object=scene["object"]["name"], container=scene["container"],
                table=scene["table"]["name"], split=scene["split"], kind=ep["kind"], seed=int(seed),
                success=bool(rec.success[-1]), length=int(len(rec.action)), demo_from=int(rec.demo_from),
            )
            start, end = writer.write_episode(meta, vars(rec))
            metas.append({**meta, "shard": Path(job["path"]).name, "start_ns": start, "end_ns": end})
            stats["written"] += 1
            stats["frames"] += len(rec.action) + 1
        writer.close()
    except BaseException:
        writer.abort()
        raise
    stats["seconds"] = time.perf_counter() - t0
    return {"task": job["task"], "episodes": metas, "stats": stats}
