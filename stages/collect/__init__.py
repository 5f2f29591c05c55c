"""collect: planned robot trajectories in ManiSkill3 scenes, recorded into MCAP shards.

Four tabletop tasks (pick & place, push, pull, move to aim) in scenes built from primitives
(object x container x table, ``catalog.py``); optimal trajectories through the essential waypoints,
the paper's three suboptimal kinds, and two failure kinds, near-misses (the end beside the goal) and
grasp-misses (the grasp or contact beside the object) (``plans.py``; labelled negatives of the world
model, never demonstrations), planned by MPLib and recorded as delta-EE
actions under ``pd_ee_delta_pose`` (``execute.py``), one shard per worker task (``worker.py``).

Inputs:
    none (the first stage).

Outputs:
    ``scenes.json``      the scene catalog and its IND/OOD split;
    ``sim.json``         image size, robot mesh, controller: every later simulator reads them here;
    ``shards/*.mcap``    episodes (both camera views as PNG CompressedImage, actions, EE pose,
                         joints, reward, success); schema in docs/mcap_schema.md;
    ``episodes.jsonl``   the episode index (``dataset.EpisodeMeta`` per line);
    ``metrics.json``     counts, planner / execution success, retries, replay success, wall time.
    Read it with ``stages.collect.dataset.Dataset``.

Key includes:
    the catalog (shapes, sizes, colors, tables, split), scene/episode counts, image size, robot
    mesh, retry and step limits, seed. Not ``jobs`` (parallelism never changes the data).

Toy profile:
    all four tasks on 1 IND and 1 OOD scene, one optimal + one suboptimal + one near-miss + one
    grasp-miss trajectory per scene and task (32 episodes), every successful optimal episode replayed
    open-loop; ~2 min on 2 cores. The defaults (``small``): 24 IND + 8 OOD scenes, 896 episodes
    (docs/collect.md says why).
"""
from __future__ import annotations

import json
import time
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from pipeline.context import StageContext
from stages.collect.plans import KINDS, SUBOPTIMAL_KINDS
from stages.collect.tasks import TASKS, Task



class Config(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, description="seed for scene sampling, initial states and plan perturbations")
    tasks: tuple[Task, ...] = Field(TASKS, description="tasks to collect")
    image_size: int = Field(64, ge=16, le=512, description="side of both square camera images (pixels)")
    robot_mesh: Literal["lowpoly", "stock"] = Field("lowpoly", description="Panda visual meshes: lowpoly (~4x faster rendering) or stock")
    shapes: tuple[str, ...] = Field(("cube", "cylinder", "sphere", "capsule"), description="object shapes of the catalog")
    sizes: dict[str, float] = Field({"small": 0.022, "large": 0.03}, description="size name -> half extent (m)")
    colors: dict[str, tuple[float, float, float]] = Field(
        {"red": (0.85, 0.1, 0.1), "green": (0.1, 0.7, 0.2), "blue": (0.15, 0.3, 0.9), "yellow": (0.95, 0.8, 0.1)},
        description="color name -> RGB in [0, 1]",
    )
    tables: dict[str, tuple[float, float, float]] = Field(
        {"wood": (0.55, 0.4, 0.25), "dark grey": (0.3, 0.3, 0.33)}, description="table name -> RGB in [0, 1]"
    )
    ood_objects: int = Field(4, ge=1, description="objects held out entirely (OOD: unseen objects)")
    ood_pairs: int = Field(6, ge=0, description="(IND object, container) pairs held out (OOD: unseen combinations)")
    split_seed: int = Field(0, description="seed of the IND/OOD split (kept apart from `seed` so the split is stable)")
    ind_scenes: int = Field(24, ge=0, description="IND scenes to collect in (0 = all)")
    ood_scenes: int = Field(8, ge=0, description="OOD scenes to collect in (0 = none)")
    optimal_per_scene: int = Field(3, ge=1, description="optimal trajectories per IND scene and task")
    ood_optimal_per_scene: int = Field(1, ge=0, description="optimal trajectories per OOD scene and task")
    suboptimal_ratio: float = Field(1.0, ge=0, description="suboptimal:optimal trajectory ratio (paper 1:1); kinds cycle")
    max_steps: int = Field(400, ge=50, description="step limit of one trajectory")
    max_retries: int = Field(3, ge=0, description="new seeds tried after a failed plan or an unsuccessful execution")
    near_miss_per_scene: int = Field(1, ge=0, description="near-miss failures per scene and task (IND and OOD): "
                                     "labelled done-head negatives, never demonstrations (plans.near_miss_plan)")
    grasp_miss_per_scene: int = Field(1, ge=0, description="grasp-miss failures per scene and task (IND and OOD): the "
                                      "gripper closes / slides beside the object; labelled negatives of the world model, "
                                      "never demonstrations (plans.grasp_miss_plan)")
    recover_per_scene: int = Field(0, ge=0, description="recovery demonstrations per IND scene and task: the plan "
                                   "first closes / comes down in the wrong place, then recovers and succeeds "
                                   "(plans.recover_plan); used by SFT only where sft.kinds names 'recover'")
    keep_failed: bool = Field(False, description="also write episodes whose execution did not succeed")
    replay_fraction: float = Field(0.1, ge=0, le=1, description="fraction of successful optimal episodes replayed open-loop to verify actions")
    episodes_per_shard: int = Field(8, ge=1, description="episodes per MCAP shard (one worker task)")


def scene_catalog(cfg: Config):
    """All scenes of the config's catalog, with the IND/OOD split."""
    from stages.collect.catalog import build_catalog

    return build_catalog(cfg.shapes, cfg.sizes, cfg.colors, cfg.tables, ood_objects=cfg.ood_objects,
                         ood_pairs=cfg.ood_pairs, split_seed=cfg.split_seed)


RECOVER_SEED_OFFSET = 5_000_000  # recovery episodes' seeds: cfg.seed * 10**7 + this + their count (retries stay below 10**7)


def plan_jobs(cfg: Config, scenes, shard_dir) -> list[dict]:
    """Shard jobs: every (task, scene, kind, index) episode with its seed, grouped by task."""
    rng = np.random.default_rng(cfg.seed)
    ind = [s for s in scenes if s.split == "ind"]
    ood = [s for s in scenes if s.split == "ood"]
    ind = [ind[i] for i in rng.permutation(len(ind))][: cfg.ind_scenes or len(ind)]
    ood = [ood[i] for i in rng.permutation(len(ood))][: cfg.ood_scenes]
    jobs = []
    n = n_recover = 0
    for task in cfg.tasks:
        episodes = []
        for scene, n_opt in [(s, cfg.optimal_per_scene) for s in ind] + [(s, cfg.ood_optimal_per_scene) for s in ood]:
            n_sub = int(round(n_opt * cfg.suboptimal_ratio))
            kinds = (["optimal"] * n_opt + [SUBOPTIMAL_KINDS[(n + j) % 3] for j in range(n_sub)]
                     + ["near_miss"] * cfg.near_miss_per_scene + ["grasp_miss"] * cfg.grasp_miss_per_scene)
            for j, kind in enumerate(kinds):
                episodes.append(dict(
                    episode_id=f"{task}.{scene.scene_id}.{kind}.{j}", scene=scene.to_dict(), kind=kind,
                    seed=int(cfg.seed * 10**7 + n), replay=bool(kind == "optimal" and rng.random() < cfg.replay_fraction),
                ))
                n += 1
            for j in range(cfg.recover_per_scene if scene.split == "ind" else 0):
                # seeds of their own range: every other episode is the one the config without them plans
                episodes.append(dict(
                    episode_id=f"{task}.{scene.scene_id}.recover.{len(kinds) + j}", scene=scene.to_dict(), kind="recover",
                    seed=int(cfg.seed * 10**7 + RECOVER_SEED_OFFSET + n_recover), replay=False,
                ))
                n_recover += 1
        for k in range(0, len(episodes), cfg.episodes_per_shard):
            name = f"{task}-{k // cfg.episodes_per_shard:04d}.mcap"
            jobs.append(dict(
                path=str(shard_dir / name), task=task, image_size=cfg.image_size, robot_mesh=cfg.robot_mesh,
                max_steps=cfg.max_steps, max_retries=cfg.max_retries, keep_failed=cfg.keep_failed,
                episodes=episodes[k: k + cfg.episodes_per_shard],
            ))
    return jobs


def _rate(num: int, den: int) -> float | None:
    return None if den == 0 else num / den


def run(ctx: StageContext) -> None:
    from stages.collect.catalog import write_scenes_json
    from stages.collect.dataset import SHARD_DIR, EpisodeMeta, SimFacts, write_index, write_sim_facts
    from stages.collect.resume import collect_or_resume

    cfg: Config = ctx.config
    t0 = time.perf_counter()
    scenes = scene_catalog(cfg)
    write_scenes_json(scenes, ctx.out / "scenes.json")
    write_sim_facts(ctx.out, SimFacts(image_size=cfg.image_size, robot_mesh=cfg.robot_mesh))
    shard_dir = ctx.out / SHARD_DIR
    shard_dir.mkdir(parents=True, exist_ok=True)
    jobs = plan_jobs(cfg, scenes, shard_dir)
    checkpoints = ctx.checkpoints()
    for job in jobs:  # each finished shard is a checkpoint: a killed run resumes at the next shard (stages.collect.resume)
        job["checkpoints"] = None if checkpoints.root is None else str(checkpoints.root)
    n_planned = sum(len(j["episodes"]) for j in jobs)
    ctx.log.info("collect: %d episodes in %d shards, %d workers", n_planned, len(jobs), ctx.jobs)
    if ctx.mapper is not None and ctx.jobs > 1:
        results = ctx.map(collect_or_resume, jobs, desc="collect shards")
    else:  # in-process: a per-trajectory bar with the rates
        results = []
        with ctx.progress(n_planned, "collect", unit="traj") as bar:
            for job in jobs:
                results.append(collect_or_resume(job))
                st = [r["stats"] for r in results]
                attempts = sum(s["attempts"] for s in st)
                bar.update(len(job["episodes"]))
                bar.postfix(traj_s=f"{bar.rate:.2f}", planner_ok=f"{1 - sum(s['plan_failures'] for s in st) / max(attempts, 1):.2f}")

    metas = [EpisodeMeta.from_dict(m) for r in results for m in r["episodes"]]
    write_index(ctx.out, metas)
    wall = time.perf_counter() - t0
    per_task = {}
    for task in cfg.tasks:
        st = [r["stats"] for r in results if r["task"] == task]
        tot = {k: sum(s[k] for s in st) for k in st[0]} if st else {}
        per_task[task] = dict(
            episodes=tot.get("written", 0), frames=tot.get("frames", 0), attempts=tot.get("attempts", 0),
            retries=tot.get("retries", 0), dropped=tot.get("dropped", 0),
            plan_failures=tot.get("plan_failures", 0), exec_failures=tot.get("exec_failures", 0),
            failure_unintended_successes=tot.get("unintended_successes", 0),
            planner_success_rate=_rate(tot.get("attempts", 0) - tot.get("plan_failures", 0), tot.get("attempts", 0)),
            execution_success_rate=_rate(tot.get("attempts", 0) - tot.get("plan_failures", 0) - tot.get("exec_failures", 0),
                                         tot.get("attempts", 0) - tot.get("plan_failures", 0)),
            replayed=tot.get("replayed", 0), replay_success_rate=_rate(tot.get("replay_success", 0), tot.get("replayed", 0)),
            replay_exact_rate=_rate(tot.get("replay_exact", 0), tot.get("replayed", 0)),
        )
    tot = lambda k: sum(p[k] for p in per_task.values())  # noqa: E731
    attempts = tot("attempts")
    metrics = dict(
        episodes=len(metas), episodes_planned=n_planned, frames=tot("frames"),
        episodes_by_split={s: sum(m.split == s for m in metas) for s in ("ind", "ood")},
        episodes_by_kind={k: sum(m.kind == k for m in metas) for k in KINDS},
        scenes=len(scenes), scenes_collected=len({m.scene_id for m in metas}),
        attempts=attempts, retries=tot("retries"), dropped=tot("dropped"),
        failure_unintended_successes=tot("failure_unintended_successes"),
        planner_success_rate=_rate(attempts - tot("plan_failures"), attempts),
        execution_success_rate=_rate(attempts - tot("plan_failures") - tot("exec_failures"), attempts - tot("plan_failures")),
        replayed=tot("replayed"),
        replay_success_rate=_rate(sum(r["stats"]["replay_success"] for r in results), tot("replayed")),
        per_task=per_task, wall_seconds=wall, shards_resumed=sum(bool(r.get("resumed")) for r in results),
        # rates over what this run collected (a resumed shard took no time here)
        trajectories_per_second=sum(len(r["episodes"]) for r in results if not r.get("resumed")) / wall,
        frames_per_second=sum(r["stats"]["frames"] for r in results if not r.get("resumed")) / wall,
    )
    ctx.write_metrics(metrics)
    ctx.log.info("collect: %d episodes, %.2f traj/s, planner success %.3f, replay success %s, %.0f s",
                 len(metas), metrics["trajectories_per_second"], metrics["planner_success_rate"] or 0.0,
                 metrics["replay_success_rate"], wall)
    if not metas:
        raise RuntimeError(f"collect wrote no episodes ({n_planned} planned); metrics: {json.dumps(metrics)}")
