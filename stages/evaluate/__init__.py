"""evaluate: success of the trained policies back in the simulator, in-domain and out-of-domain,
with the paper's table layouts, figures and rollout GIFs.

Each policy (the sft stage's behaviour-cloned ``sft`` policy and the rl stage's ``ppo`` policy
trained with ``rl.reward``) runs in ManiSkill with the task's own success check: in-domain (the
training scenes, initial states never used in collection) and out-of-domain (the catalog's held-out
scenes: unseen objects and unseen object-container pairs), plus any ``extra_scenes``. Success rates
carry their episode counts and 95% Wilson intervals. Episodes fan out with ``ctx.map`` (processes,
or Ray tasks under ``--executor ray``).

Inputs:
    collect -- scene catalog and split (scenes.json), which scenes were trained on
    tokenize -- the tokenizer (the policy's observation function)
    train_wm -- the action WM (extreme-action figure), its split; not read with
                ``world_model_figure: false`` (``unread_needs``), so a ManiSkill-only rl run
                (``stages.rl.reads_world_model``) is evaluated without building a world model
    sft -- sft_policy.pt, text embeddings (instructions)
    rl -- policy.zip, snapshots/, rl.json (reward module, method),
          training.png, reward_diagnostics.png

Outputs:
    results.jsonl          one line per evaluated episode (policy, task, scene, split, seed, success, steps)
    metrics.json           success/<policy>/<task|all>/<split>{,_lo,_hi,_n} and the run's settings
    report.md, report.html Table 1 layout (rows: methods; columns: IND/OOD x tasks), Table 2 when the
                           policy is multi-task, success vs training wall time (Fig. 2), reward
                           curves (Fig. 3), rollout GIFs (Figs. 4-5), extreme actions (Fig. 9)
    *.png, *.gif           the figures the report shows

Key includes:
    this config (episode counts, horizon, seeds, extra scenes: their content, not a file path) and
    the keys of collect, tokenize, train_wm (when read), sft and rl. Adding evaluation scenes reruns only evaluate.

Toy profile:
    2 episodes per (policy, task, split), 1 snapshot episode, horizon 20.
"""
from __future__ import annotations

import json
import shutil
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from stages.evaluate.scenes import ExtraScene, load_extra_scenes


class Config(BaseModel):
    """evaluate stage configuration (defaults sized for the ``small`` profile)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, ge=0, lt=60, description="base of the evaluation episodes' seeds (kept far from collection "
                      "seeds); 60 and up are the rl stage's acceptance-test states (stages/rl/acceptance.py)")
    episodes: int = Field(25, ge=1, description="episodes per (policy, task, split); the same initial states for every policy")
    max_steps: int = Field(75, ge=1, description="episode horizon in policy steps of frame_skip control steps each "
                           "(planner demos take ~100-280 control steps = 25-70 policy steps at frame_skip 4)")
    policies: list[Literal["sft", "ppo"]] = Field(["sft", "ppo"], min_length=1, description="which rl outputs to evaluate")
    splits: list[Literal["ind", "ood", "extra"]] = Field(["ind", "ood", "extra"], min_length=1)
    snapshot_episodes: int = Field(4, ge=0, description="episodes per (snapshot, split) for success vs training time")
    extra_scenes: list[ExtraScene] = Field([], description="more OOD scenes (a list, or a path to a YAML list)")
    videos: bool = Field(True, description="a GIF of the first IND and the first OOD episode of each task, per policy")
    image_size: int | None = Field(None, ge=16, description="camera size; None = collect's (sim.json), "
                                   "any other value must equal it")
    robot_mesh: Literal["lowpoly", "stock"] | None = Field(None, description="None = collect's; any other value must equal it")
    world_model_figure: bool = Field(True, description="the action world model under extreme actions (Fig. 9); "
                                     "false: train_wm is not read, not waited for and not keyed")

    @field_validator("extra_scenes", mode="before")
    @classmethod
    def _read_file(cls, v):
        return load_extra_scenes(v)


def unread_needs(cfg: Config) -> list[str]:
    """The declared inputs this config does not read (``pipeline.plan.Project.used_needs``): train_wm
    feeds only the extreme-action figure."""
    return [] if cfg.world_model_figure else ["train_wm"]


SEED_BASE = 1_000_000  # collection seeds are small; evaluation states are new ones


def run(ctx) -> None:
    from stages.evaluate.jobs import build_jobs, environment_groups, snapshot_jobs, ungroup
    from stages.evaluate.episodes import close_sims, run_group
    from stages.evaluate.writeup import write_everything

    from stages.rl import read_rl_facts
    from stages.sft import read_policy_json

    cfg: Config = ctx.config
    rl_dir = ctx.input("rl")
    policy = read_policy_json(ctx.input("sft"))  # the facts the sft stage fixed: tasks, control steps per policy step
    facts = {"method": read_rl_facts(rl_dir)["method"], "tasks": policy["tasks"], "frame_skip": int(policy["frame_skip"])}
    jobs = build_jobs(ctx, cfg, facts)
    snaps = snapshot_jobs(ctx, cfg, facts)
    ctx.log.info("evaluate: %d jobs (%d episodes) + %d snapshot jobs", len(jobs), sum(len(j.seeds) for j in jobs), len(snaps))
    todo = jobs + snaps
    groups = environment_groups(todo)
    try:
        done = ctx.map(run_group, [[todo[i] for i in g] for g in groups], desc="evaluate scenes")
        results = [r for rs in ungroup(done, groups) for r in rs]
    finally:
        close_sims()  # the in-process (jobs=1) path keeps its simulator between jobs
    with open(ctx.out / "results.jsonl", "w") as f:
        for r in results:
            f.write(json.dumps({k: v for k, v in r.items() if k != "frames"}) + "\n")
    metrics = write_everything(ctx, cfg, facts, results)
    for name in ("training.png", "reward_diagnostics.png"):
        if (rl_dir / name).is_file():
            shutil.copyfile(rl_dir / name, ctx.out / name)
    ctx.write_metrics(metrics)


__all__ = ["Config", "run", "unread_needs", "SEED_BASE"]
