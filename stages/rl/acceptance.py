"""An acceptance test after PPO: the PPO policy replaces the SFT policy only if it does better on
validation states it never trained on (a safe-policy-improvement check, ``rl.accept_episodes``).

Why: with the `small` budget the PPO seed alone moves the in-domain success by 0.15 on one SFT policy
(docs/RESULTS.md), in either direction; a run that made the policy worse should not ship it.

How: the SFT policy and the final PPO policy each run ``accept_episodes`` deterministic episodes per
task in ManiSkill from the same IND initial states, with the evaluate stage's own jobs
(``stages.evaluate.jobs``) at evaluate seed ``ACCEPT_SEED + rl.seed``: initial states from
1,000,000 + (60 + seed) x 100,000 on, apart from evaluation's (``evaluate.seed`` below 60), the
play's (5,000,000 + 1,000 x seed) and PPO's own (random resets of the training environments). The
paired difference (PPO minus SFT on the same states, ``stages.sweep_report.paired``) decides: PPO is
kept if it exceeds ``accept_margin``, else the SFT policy's weights are saved as ``policy.zip``. The
test costs simulator episodes, also for the world-model rewards (whose PPO is otherwise
simulator-free): the stage counts them in ``accept/episodes`` and ``accept/seconds``.
"""
from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import torch

ACCEPT_SEED = 60  # evaluate-seed offset of the validation states


def decide(sft_rows: list[dict], ppo_rows: list[dict], margin: float) -> dict:
    """The paired comparison of two policies' episodes on the same states and which policy to keep."""
    from stages.sweep_report.paired import pair_up, paired_difference

    pairs = pair_up(ppo_rows, sft_rows)  # (PPO episode, SFT success) on each shared initial state
    if not pairs:
        raise ValueError("the acceptance test's SFT and PPO episodes share no initial state")
    diff = paired_difference([(bool(r["success"]), base) for r, base in pairs])
    by_task = {}
    for task in sorted({r["task"] for r, _ in pairs}):
        mine = [(bool(r["success"]), base) for r, base in pairs if r["task"] == task]
        by_task[task] = {"episodes": len(mine), "sft": sum(b for _, b in mine) / len(mine),
                         "ppo": sum(a for a, _ in mine) / len(mine)}
    return {"difference": diff, "by_task": by_task, "margin": margin,
            "sft_success": sum(b for _, b in pairs) / len(pairs),
            "ppo_success": sum(bool(r["success"]) for r, _ in pairs) / len(pairs),
            "kept": "ppo" if diff["diff"] > margin else "sft"}


def validation_config(cfg):
    """The evaluate stage's config for the acceptance test's episodes (rl config ``cfg``)."""
    from stages.evaluate import Config as EvaluateConfig

    ecfg = EvaluateConfig(episodes=cfg.accept_episodes, policies=["sft", "ppo"], splits=["ind"], videos=False,
                          max_steps=cfg.max_episode_steps, snapshot_episodes=0)
    # the validation seeds lie where users may not put `evaluate.seed` (>= 60): set past the validator
    return ecfg.model_copy(update={"seed": ACCEPT_SEED + cfg.seed})


def acceptance_test(ctx, cfg, inp, policy_dir: Path) -> tuple[dict, list[dict]]:
    """Run the validation episodes of the SFT policy and of ``policy_dir/policy.zip``; (decision, episodes)."""
    from stages.evaluate.episodes import close_sims, run_job
    from stages.evaluate.jobs import build_jobs

    dirs = {"collect": ctx.input("collect"), "tokenize": ctx.input("tokenize"), "sft": ctx.input("sft"), "rl": Path(policy_dir)}
    shim = SimpleNamespace(input=lambda name: dirs[name], device=inp.device)
    ecfg = validation_config(cfg)
    jobs = build_jobs(shim, ecfg, {"tasks": inp.tasks, "frame_skip": inp.sft_info["frame_skip"]})
    t0 = time.perf_counter()
    rows = []
    threads = torch.get_num_threads()  # the evaluate jobs' simulator pins one thread (a worker's setting):
    try:  # the rest of the stage gets its own count back
        with ctx.progress(sum(len(j.seeds) for j in jobs), "rl: acceptance test (SFT and PPO, IND)", unit="ep") as bar:
            for job in jobs:
                rows += run_job(job)
                bar.update(len(job.seeds))
    finally:
        close_sims()
        torch.set_num_threads(threads)
    result = decide([r for r in rows if r["policy"] == "sft"], [r for r in rows if r["policy"] == "ppo"], cfg.accept_margin)
    result.update({"episodes": len(rows), "seconds": time.perf_counter() - t0, "evaluate_seed": ecfg.seed})
    return result, rows
