"""Which policy runs in which scene with which seeds: the evaluation plan as ``Job``s."""
from __future__ import annotations

import json
from pathlib import Path

from stages.evaluate.episodes import Job


def scenes_by_split(ctx, cfg, tasks: list[str]) -> dict[tuple[str, str], list[dict]]:
    """(task, split) -> scene dicts: IND = scenes trained on; OOD = the catalog's held-out scenes; extra."""
    from stages.collect.catalog import read_scenes_json
    from stages.evaluate.scenes import to_scene
    from stages.goals.environments import list_environments

    catalog = read_scenes_json(ctx.input("collect") / "scenes.json")
    envs = list_environments(ctx.input("collect"), tasks)
    tables = {s.table.name: s.table.color for s in catalog.values()}
    sizes = {s.object.name.split()[0]: s.object.half_size for s in catalog.values()}  # names read "<size> <color> <shape>"
    extra = [to_scene(e, i, tables, sizes) for i, e in enumerate(cfg.extra_scenes)]
    out = {}
    for task in tasks:
        out[(task, "ind")] = [catalog[e.scene_id].to_dict() for e in envs if e.task == task and e.split == "ind"]
        out[(task, "ood")] = [s.to_dict() for s in sorted(catalog.values(), key=lambda s: s.scene_id) if s.split == "ood"]
        out[(task, "extra")] = extra
    return out


def _text(ctx) -> dict:
    from stages.sft import TEXT_EMBEDDINGS

    return json.loads((ctx.input("sft") / TEXT_EMBEDDINGS).read_text())


def policy_paths(ctx) -> dict[str, Path]:
    """Evaluated policy label -> file: the sft stage's policy and the rl stage's PPO policy."""
    from stages.sft.policy import POLICY_FILE

    return {"sft": ctx.input("sft") / POLICY_FILE, "ppo": ctx.input("rl") / "policy.zip"}


def sim_settings(ctx, cfg) -> tuple[int, str]:
    """(image size, robot mesh): collect's (sim.json); evaluate's own values, when set, must agree."""
    from stages.collect.dataset import read_sim_facts

    facts = read_sim_facts(ctx.input("collect"))
    for name, mine, theirs in (("image_size", cfg.image_size, facts.image_size), ("robot_mesh", cfg.robot_mesh, facts.robot_mesh)):
        if mine is not None and mine != theirs:
            raise ValueError(f"evaluate.{name} = {mine!r} but collect rendered with {name} = {theirs!r}: the policy "
                             f"would see frames unlike its training data; unset evaluate.{name} or set it to {theirs!r}")
    return facts.image_size, facts.robot_mesh


def _spread(policy: str, path: Path, task: str, split: str, scenes: list[dict], n: int, seed0: int, ctx, cfg,
            text: dict, record: bool, repeat: int) -> list[Job]:
    """``n`` episodes round-robin over ``scenes``, one Job per scene; ``repeat`` = control steps per policy step."""
    from stages.sft import read_policy_json

    seeds: dict[str, list[int]] = {}
    for i in range(n):
        seeds.setdefault(scenes[i % len(scenes)]["scene_id"], []).append(seed0 + i)
    by_id = {s["scene_id"]: s for s in scenes}
    image_size, robot_mesh = sim_settings(ctx, cfg)
    frame = read_policy_json(ctx.input("sft")).get("frame", "current")  # the rl policy observes as its SFT start did
    jobs = []
    for k, (sid, ss) in enumerate(sorted(seeds.items())):
        jobs.append(Job(policy, str(path), str(ctx.input("tokenize")), text, task, by_id[sid], split, ss,
                        cfg.max_steps, repeat, image_size, robot_mesh,
                        record=[ss[0]] if record and k == 0 else [], device=ctx.device, frame=frame))
    return jobs


def build_jobs(ctx, cfg, facts: dict) -> list[Job]:
    from stages.evaluate import SEED_BASE

    tasks = list(facts["tasks"])
    scenes = scenes_by_split(ctx, cfg, tasks)
    text = _text(ctx)
    paths = policy_paths(ctx)
    jobs = []
    for policy in cfg.policies:
        path = paths[policy]
        for split in cfg.splits:
            for ti, task in enumerate(tasks):
                if not scenes[(task, split)]:
                    continue
                record = cfg.videos and split in ("ind", "ood")  # the first episode of each task
                seed0 = SEED_BASE + cfg.seed * 100_000 + ti * 10_000 + ("ind", "ood", "extra").index(split) * 1_000
                jobs += _spread(policy, path, task, split, scenes[(task, split)], cfg.episodes, seed0, ctx, cfg, text, record,
                                int(facts["frame_skip"]))
    return jobs


def snapshot_jobs(ctx, cfg, facts: dict) -> list[Job]:
    """Each PPO snapshot on IND and OOD (few episodes, tasks pooled): success vs training time."""
    from stages.evaluate import SEED_BASE

    index = ctx.input("rl") / "snapshots" / "index.json"
    if not cfg.snapshot_episodes or not index.is_file():
        return []
    tasks = list(facts["tasks"])
    scenes = scenes_by_split(ctx, cfg, tasks)
    text = _text(ctx)
    jobs = []
    for snap in json.loads(index.read_text()):
        for split in ("ind", "ood"):
            for ti, task in enumerate(tasks):
                n = cfg.snapshot_episodes // len(tasks) + (ti < cfg.snapshot_episodes % len(tasks))
                if n and scenes[(task, split)]:
                    seed0 = SEED_BASE + 50_000 + cfg.seed * 100_000 + ti * 1_000 + (split == "ood") * 500
                    jobs += _spread(f"ppo@{snap['timesteps']}", ctx.input("rl") / snap["path"], task, split,
                                    scenes[(task, split)], n, seed0, ctx, cfg, text, False,
                                    int(facts["frame_skip"]))
    return jobs


def environment_groups(jobs: list[Job]) -> list[list[int]]:
    """``jobs``' indices grouped by (task, scene, split), in build order within and across groups: the
    unit of work a worker runs (``episodes.run_group``).

    Jobs are built policy by policy, so a worker taking them one at a time met another (task, scene)
    at nearly every job and rebuilt its simulator (toy: 32 builds for 40 episodes, each ~0.6 s plus
    ManiSkill's garbage collection at build and close). A group builds its scene once and runs every
    policy's jobs on it in a fixed order; a scene reused by another worker's later job would replay
    differently (docs/evaluate.md), and no two groups share a scene, so outcomes do not depend on
    which worker ran what.
    """
    groups: dict[tuple, list[int]] = {}
    for i, j in enumerate(jobs):
        groups.setdefault((j.task, j.scene["scene_id"], j.split), []).append(i)
    return list(groups.values())


def ungroup(done: list[list], groups: list[list[int]]) -> list:
    """``done[g][k]`` is the result of job ``groups[g][k]``: the results in the jobs' own order."""
    out = [None] * sum(len(g) for g in groups)
    for group, results in zip(groups, done):
        for i, r in zip(group, results, strict=True):
            out[i] = r
    return out
