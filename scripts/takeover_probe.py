"""Can the planner finish an episode from where the SFT policy stopped?

The SFT policy's failed episodes mostly end with the policy at rest (the evaluate stage's "came to
rest": commanded |delta position| below ``REST_ACTION`` for ``REST_STEPS`` policy steps running).
Demonstrations that continue from such states (DAgger with the planner as the expert) exist only if
the collect stage's planner can act from them. This probe reruns the failed episodes of a
fresh-state file (``scripts/evaluate_sft.py``; the deterministic policy reproduces them) up to the
moment the policy comes to rest (or to the episode's end), hands the simulator to the planner
(``stages.common.takeover``: the rest of the task planned from the current object and gripper state, as
``stages.collect.plans`` plans it from a reset) and records whether the planner's continuation
succeeds, per task.

    PYTHONPATH=. .venv/bin/python scripts/takeover_probe.py COLLECT TOKENIZE SFT --file F --out OUT.jsonl
        [--per-task 12] [--max-steps 75] [--seed 1]
    PYTHONPATH=. .venv/bin/python scripts/takeover_probe.py --summarize OUT.jsonl [OUT2.jsonl ...]

``--file``: the SFT policy's own fresh-state file (its rows name the states; only failed rows are
rerun). ``--seed``: the evaluate plan's seed the file was made with (evaluate_sft.py's ``--seed``).
A rerun appends to ``--out`` and skips the states already there.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from stages.common.takeover import take_over  # noqa: E402
from stages.common.rest import REST_ACTION, REST_STEPS  # noqa: E402


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--summarize"]:
        return summarize(*map(Path, argv[1:]))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("collect", type=Path)
    p.add_argument("tokenize", type=Path)
    p.add_argument("sft", type=Path)
    p.add_argument("--file", type=Path, required=True, help="the SFT policy's fresh-state file")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--per-task", type=int, default=12, help="failed episodes rerun per task and split")
    p.add_argument("--max-steps", type=int, default=75, help="the file's --max-steps")
    p.add_argument("--seed", type=int, default=1, help="the evaluate plan's seed of the file")
    p.add_argument("--plan-steps", type=int, default=400, help="control steps the planner may use")
    a = p.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    from flip_strips import jobs_for, state
    from fresh_state_table import episodes

    from stages.evaluate.episodes import _policy_for, _sim_for, _spec
    from stages.sft.policy import act

    rows = episodes(a.file)
    counts: dict = {}
    for r in rows:
        counts[(r["task"], r["split"])] = counts.get((r["task"], r["split"]), 0) + 1
    chosen, per = [], {}
    for r in rows:
        k = (r["task"], r["split"])
        if not r["success"] and per.get(k, 0) < a.per_task:
            per[k] = per.get(k, 0) + 1
            chosen.append(state(r))
    args = SimpleNamespace(collect=a.collect, tokenize=a.tokenize, seed=a.seed, max_steps=a.max_steps)
    jobs = jobs_for(chosen, "sft", None, a.sft, args, counts)
    done = set()
    if a.out.exists():
        done = {(r["task"], r["scene_id"], r["seed"]) for r in map(json.loads, a.out.read_text().splitlines())}
    with a.out.open("a") as fh:
        for n, job in enumerate(jobs):
            sim, model, spec = _sim_for(job), _policy_for(job), _spec(job)
            for seed in job.seeds:
                if (job.task, str(job.scene["scene_id"]), seed) in done:
                    continue
                obs, info = sim.reset(seed=seed, options={"spec": spec})
                success, steps, run = bool(info["success"]), 0, 0
                while not success and steps < job.max_steps and run < REST_STEPS:
                    action = act(model, {k: v[None] for k, v in obs.items()})[0]
                    run = run + 1 if np.linalg.norm(action[:3]) < REST_ACTION else 0
                    obs, _, success, truncated, info = sim.step(action)
                    steps += 1
                    if truncated:
                        break
                row = {"task": job.task, "scene_id": str(job.scene["scene_id"]), "split": job.split, "seed": seed,
                       "policy_steps": steps, "rested": run >= REST_STEPS, "policy_success": bool(success)}
                if not success:
                    took = take_over(sim.env.env, a.plan_steps)  # the ManiSkill env under the observation wrapper
                    row.update(grasped=took.grasped, remaining=round(took.remaining, 4))
                    if took.recording is None:
                        row.update(takeover="no_plan", error=took.error)
                    else:
                        row.update(takeover="success" if took.success else "failed",
                                   control_steps=len(took.recording.action))
                fh.write(json.dumps(row) + "\n")
                fh.flush()
            print(f"job {n + 1}/{len(jobs)} {job.task} {job.split}", flush=True)
    summarize(a.out)


def summarize(*paths: Path) -> None:
    """Per task and split, then over all rows: how often the planner finished, with Wilson intervals."""
    from stages.evaluate.stats import wilson

    def share(rs: list[dict]) -> str:
        k = sum(r["takeover"] == "success" for r in rs)
        if not rs:
            return "-"
        _, lo, hi = wilson(k, len(rs))
        return f"{k}/{len(rs)} [{lo:.2f}, {hi:.2f}]"

    rows = [json.loads(line) for p in paths for line in p.read_text().splitlines() if line.strip()]
    print("| task | split | rerun | policy succeeded (mismatch) | rested | planner finished | no plan | finished, rested only |")
    print("|---|---|---|---|---|---|---|---|")
    keys = sorted({(r["task"], r["split"]) for r in rows})
    for key in [*keys, ("all", "all")]:
        rs = [r for r in rows if key == ("all", "all") or (r["task"], r["split"]) == key]
        took = [r for r in rs if "takeover" in r]
        rested = [r for r in took if r["rested"]]
        print(f"| {key[0]} | {key[1]} | {len(rs)} | {sum(r['policy_success'] for r in rs)} | {len(rested)} | "
              f"{share(took)} | {sum(r['takeover'] == 'no_plan' for r in took)} | {share(rested)} |")


if __name__ == "__main__":
    main()
