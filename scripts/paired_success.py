"""PPO minus SFT, paired on the same initial states, from evaluate artifacts given by path.

The sweep report does this for a sweep's points; this script does it for any evaluate artifacts,
e.g. PPO policies evaluated with ``evaluate.policies: [ppo]`` against the SFT episodes of another
evaluate artifact with the same ``evaluate.seed`` and ``episodes`` (hence the same initial states):

    .venv/bin/python scripts/paired_success.py --sft <evaluate dir> <evaluate dir> [<evaluate dir> ...]

Any of them may instead be a results file written by ``scripts/evaluate_sft.py --out``. Several
seeds, each PPO policy paired with its own SFT policy: give ``--sft`` one baseline per compared
artifact, in the same order (``--sft s0 s1 s2 -- p0 p1 p2``); the pooled lines pool those pairs.
Two PPO policies against each other (e.g. ``wm`` minus ``rule``): ``--baseline-policy ppo``.

Prints, per evaluate artifact and pooled, the success difference per split (tasks pooled) and per
task and split: mean [95% interval] (n, states only PPO solved / only SFT solved); with several
compared artifacts (seeds), also the mean of their differences with a Student-t interval over them
(what another seed would give: stages/sweep_report/paired.py).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages.sweep_report.paired import across_seeds, by_split, fmt_across_seeds, fmt_difference, pair_up  # noqa: E402


def results(ev: Path, policy: str) -> list[dict]:
    """``policy``'s episodes of an evaluate artifact, or of a results file (``scripts/evaluate_sft.py --out``)."""
    path = Path(ev) if Path(ev).is_file() else Path(ev) / "results.jsonl"
    if not path.is_file():
        raise SystemExit(f"{path} is missing: is {ev} a committed evaluate artifact?")
    return [r for r in map(json.loads, path.read_text().splitlines()) if r["policy"] == policy]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sft", type=Path, nargs="+", required=True,
                    help="evaluate artifact(s) whose 'sft' episodes are the baseline: one for all, or one per compared artifact")
    ap.add_argument("evaluate", type=Path, nargs="+", help="evaluate artifacts whose 'ppo' episodes are compared")
    ap.add_argument("--policy", default="ppo", help="policy name in results.jsonl to compare (default ppo)")
    ap.add_argument("--baseline-policy", default="sft", help="policy name of the --sft files' episodes (default sft)")
    args = ap.parse_args()
    if len(args.sft) not in (1, len(args.evaluate)):
        raise SystemExit(f"--sft: {len(args.sft)} baselines for {len(args.evaluate)} compared artifacts; give one, or one each")
    baselines = args.sft * len(args.evaluate) if len(args.sft) == 1 else args.sft
    pooled, per_artifact = [], []
    for ev, base in zip(args.evaluate, baselines):
        sft = results(base, args.baseline_policy)
        if not sft:
            raise SystemExit(f"{base} has no {args.baseline_policy!r} episodes")
        pairs = pair_up(results(ev, args.policy), sft)
        if not pairs:
            print(f"{ev}: no episode shares an initial state with {base} (another evaluate seed or episode count?)")
            continue
        pooled += pairs
        per_artifact.append(pairs)
        print(f"{ev.name[:12]}: {len(pairs)} paired episodes")
        for (split,), res in by_split(pairs).items():
            print(f"  {split:5s} {fmt_difference(res)}")
        for (task, split), res in by_split(pairs, ("task", "split")).items():
            print(f"    {task:12s} {split:5s} {fmt_difference(res)}")
    if len(args.evaluate) > 1 and pooled:
        print("pooled:")
        for (split,), res in by_split(pooled).items():
            print(f"  {split:5s} {fmt_difference(res)}")
        print("across seeds (each compared artifact one seed; Student-t over them):")
        for split in sorted({r["split"] for r, _ in pooled}):
            diffs = [res[(split,)]["diff"] for res in (by_split(p) for p in per_artifact) if (split,) in res]
            print(f"  {split:5s} {fmt_across_seeds(across_seeds(diffs))}")


if __name__ == "__main__":
    main()
