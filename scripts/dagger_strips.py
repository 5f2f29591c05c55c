"""Look at DAgger's demonstrations: where the policy stopped and what the planner did from there.

An sft artifact trained with ``sft.dagger_rounds`` lists every start of its first round in
``dagger.jsonl``. This script reruns the first ``--starts`` of them that were handed to the planner,
with the policy that round rolled out (the same seed's sft artifact without DAgger, ``--policy``:
its first cloning is the same computation), through the stage's own ``stages.sft.dagger.run_round``,
and draws per start the planner's continuation in the third view (``--frames`` frames from the
takeover state, the first, to its end). It prints how many rerun rows equal the file's in the policy's
part (its steps, success, whether it rested: deterministic) and in the planner's (the takeover's
outcome, length and pairs: the planner falls back to RRTConnect and samples, so a continuation may differ).

    PYTHONPATH=. .venv/bin/python scripts/dagger_strips.py COLLECT TOKENIZE DAGGER_SFT --policy SFT \
        [--starts 8] [--frames 8] [--out DIR]

Writes ``DIR/<n>_<task>_<scene>_<seed>_<takeover>.png`` and ``DIR/index.md``.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

POLICY = ("policy_steps", "policy_success", "rested")  # the deterministic policy's part: reproduces exactly
PLANNER = ("takeover", "control_steps", "pairs")  # the planner's: may differ where it samples (RRTConnect, IK restarts)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("collect", type=Path)
    p.add_argument("tokenize", type=Path)
    p.add_argument("dagger_sft", type=Path, help="the sft artifact trained with dagger_rounds")
    p.add_argument("--policy", type=Path, required=True, help="the same seed's sft artifact without DAgger")
    p.add_argument("--starts", type=int, default=8, help="takeovers rerun and drawn (the file's first ones)")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--out", type=Path, default=Path("dagger_strips"))
    a = p.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    from stages.common.sim_env import sim_over
    from stages.evaluate.report import strip_figure
    from stages.goals.environments import list_environments
    from stages.sft import POLICY_JSON, TEXT_EMBEDDINGS
    from stages.sft.dagger import run_round
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, load_policy
    from stages.tokenize.tokenizer import load_tokenizer

    cfg = json.loads((a.dagger_sft / "manifest.json").read_text())["key_inputs"]["config"]
    rows = [json.loads(x) for x in (a.dagger_sft / "dagger.jsonl").read_text().splitlines()]
    chosen = [r for r in rows if r["round"] == 1 and r["takeover"] != "none"][: a.starts]
    info = json.loads((a.policy / POLICY_JSON).read_text())
    obs_fn = ObservationFn.for_policy(load_tokenizer(a.tokenize), json.loads((a.policy / TEXT_EMBEDDINGS).read_text()), info)
    envs = {e.env_id: e for e in list_environments(a.collect)}
    sim, specs = sim_over(a.collect, obs_fn, [envs[r["env_id"]] for r in chosen], max_steps=cfg["dagger_max_steps"],
                          frame_skip=cfg["frame_skip"], seed=cfg["seed"])
    seen = []
    try:
        run_round(load_policy(a.policy / POLICY_FILE), sim, specs, [r["seed"] for r in chosen],
                  max_steps=cfg["dagger_max_steps"], plan_steps=cfg["dagger_plan_steps"], frame_skip=cfg["frame_skip"],
                  min_move=cfg["retime_min_move"], max_gap=max(cfg["retime_max_gap"], cfg["frame_skip"]),
                  on_takeover=lambda row, took: seen.append((asdict(row), took.recording)))
    finally:
        sim.close()

    a.out.mkdir(parents=True, exist_ok=True)
    lines, same, same_plan = [f"# DAgger continuations of {a.dagger_sft.name[:12]} (policy {a.policy.name[:12]})", ""], 0, 0
    for n, (filed, (row, rec)) in enumerate(zip(chosen, seen)):
        diff = [k for k in POLICY + PLANNER if filed[k] != row[k]]
        same += not [k for k in diff if k in POLICY]
        same_plan += not diff
        task, scene = row["env_id"].split("/", 1)
        head = (f"policy: {row['policy_steps']} steps, {'came to rest' if row['rested'] else 'ran out of steps'}; "
                f"planner: {row['takeover']}")
        name = f"{n:02d}_{task}_{scene}_{row['seed']}_{row['takeover']}.png"
        if rec is not None:
            picks = np.linspace(0, len(rec.third) - 1, a.frames).round().astype(int)
            strip_figure([(f"{head} in {len(rec.action)} control steps, {row['pairs']} pairs", rec.third[picks])],
                         a.out / name, f"{task}, scene {scene}, seed {row['seed']}")
            lines.append(f"![{name}]({name})")
        else:
            lines.append(f"- {task} {scene} {row['seed']}: {head} (nothing to draw)")
        if diff:
            lines.append(f"  - differs from dagger.jsonl in {diff}: file {[filed[k] for k in diff]}, rerun {[row[k] for k in diff]}")
    summary = (f"rows equal to dagger.jsonl in the policy's part: {same} of {len(chosen)}, "
               f"and in the planner's too: {same_plan} of {len(chosen)}")
    lines.append(f"\n{summary[0].upper()}{summary[1:]}.")
    (a.out / "index.md").write_text("\n".join(lines) + "\n")
    print(f"{summary}; strips in {a.out} (index.md)")


if __name__ == "__main__":
    main()
