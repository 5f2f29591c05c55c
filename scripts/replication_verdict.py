"""Issue 13 target 2's replication, read against the predictions written down before it ran.

The `replication` sweep (pipeline.yaml: PPO in the world model at HEAD's defaults and PPO in ManiSkill,
seeds 0-5) and its fresh-state files (`scripts/fresh_state_sweep.py replication`) answer four
predictions and one decision, fixed in docs/RESULTS.md ("A fresh machine again; ... target 2's
replication written down before it runs") before any of its results existed. This script states
them as code, so the reading cannot drift towards the result:

1. `wm` minus SFT out of domain, pooled over the seeds: point estimate in [-0.02, +0.03], its 95%
   interval spanning 0.
2. `rule` minus SFT in domain: interval above 0.
3. `wm` minus `rule` out of domain: point estimate at or below 0.
4. Imagined-success precision (the rl stage's `imagined/<split>/precision`) below 0.5 at every point.
Decision: target 2 by PPO is met only if prediction 1's interval lies above 0 over all six seeds.

    PYTHONPATH=. .venv/bin/python scripts/replication_verdict.py [--tag TAG] [--store DIR] [--folder F]

It reads the seeds whose three policies (`sft`, the `wm` arm, `rule`) have finished files in both splits;
with fewer than six, the predictions are read on those seeds and the decision is "pending". The tag
defaults to the store's (as `fresh_state_sweep.py` names its files); precision is read from the
replication's rl artifacts that the store holds (none: "not measured yet"), and only when the files'
tag is the store's: with `--tag` naming another build (say, committed files read on a fresh machine),
that store's policies are not the files' and precision is left out.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from fresh_state_table import FRESH, Comparison, compare, dated, file_prefix  # noqa: E402

SWEEP = "replication"
SEEDS = (0, 1, 2, 3, 4, 5)   # the pre-registered seeds
RULE = f"{SWEEP}-rule"
P1_RANGE = (-0.02, 0.03)     # prediction 1's point estimate
PRECISION_BELOW = 0.5        # prediction 4


@dataclass(frozen=True)
class Reading:
    name: str          # "1".."4" or "decision"
    predicted: str
    measured: str
    holds: bool | None  # None: nothing to read yet


def _interval(r: dict) -> str:
    return f"{r['diff']:+.3f} [{r['lo']:+.3f}, {r['hi']:+.3f}] (n={r['n']:,})"


def judge(wm_sft_ood: dict | None, rule_sft_ind: dict | None, wm_rule_ood: dict | None,
          precisions: dict[str, float | None], seeds: tuple[int, ...]) -> list[Reading]:
    """The four predictions and the decision from pooled paired differences ({"diff", "lo", "hi", "n"};
    None: not measurable yet) and each point's precision by label ("<point> <split>": value or None)."""
    out = []
    if wm_sft_ood is None:
        out.append(Reading("1", "wm - SFT OOD in [-0.02, +0.03], interval spans 0", "no files yet", None))
    else:
        d, lo, hi = wm_sft_ood["diff"], wm_sft_ood["lo"], wm_sft_ood["hi"]
        out.append(Reading("1", "wm - SFT OOD in [-0.02, +0.03], interval spans 0", _interval(wm_sft_ood),
                           P1_RANGE[0] <= d <= P1_RANGE[1] and lo <= 0 <= hi))
    if rule_sft_ind is None:
        out.append(Reading("2", "rule - SFT IND, interval above 0", "no files yet", None))
    else:
        out.append(Reading("2", "rule - SFT IND, interval above 0", _interval(rule_sft_ind), rule_sft_ind["lo"] > 0))
    if wm_rule_ood is None:
        out.append(Reading("3", "wm - rule OOD at or below 0", "no files yet", None))
    else:
        out.append(Reading("3", "wm - rule OOD at or below 0", _interval(wm_rule_ood), wm_rule_ood["diff"] <= 0))
    measured = {k: v for k, v in precisions.items() if v is not None and not math.isnan(v)}
    if not measured:
        out.append(Reading("4", f"precision < {PRECISION_BELOW} at every point", "not measured yet", None))
    else:
        text = ", ".join(f"{k} {v:.2f}" for k, v in sorted(measured.items()))
        out.append(Reading("4", f"precision < {PRECISION_BELOW} at every point", text,
                           all(v < PRECISION_BELOW for v in measured.values())))
    if len(seeds) < len(SEEDS) or wm_sft_ood is None:
        out.append(Reading("decision", "target 2 by PPO met iff prediction 1's interval > 0 over six seeds",
                           f"pending: {len(seeds)} of {len(SEEDS)} seeds", None))
    else:
        met = wm_sft_ood["lo"] > 0
        out.append(Reading("decision", "target 2 by PPO met iff prediction 1's interval > 0 over six seeds",
                           f"{'met' if met else 'not met'}: lower bound {wm_sft_ood['lo']:+.3f}", met))
    return out


def wm_stem(folder: Path, tag: str) -> str | None:
    """The world-model arm's stem: the one `replication-*` stem in the tag's files other than `rule`'s."""
    name = re.compile(rf"^(?P<stem>{SWEEP}-.+?)(_ood)?_s\d+_{re.escape(tag)}_[^_]+\.jsonl$")
    stems = {m["stem"] for p in folder.iterdir() if (m := name.match(p.name))} - {RULE}
    if len(stems) > 1:
        raise SystemExit(f"{folder}: several world-model arms for tag {tag!r}: {sorted(stems)}")
    return next(iter(stems), None)


def finished_seeds(folder: Path, stems: tuple[str, ...], tag: str) -> tuple[int, ...]:
    """The pre-registered seeds whose files of every stem exist in both splits."""
    return tuple(s for s in SEEDS if all(len(dated(folder, file_prefix(stem, s, split, tag))) == 1
                                        for stem in stems for split in ("ind", "ood")))


def differences(folder: Path, tag: str) -> tuple[dict | None, dict | None, dict | None, tuple[int, ...], str | None]:
    """Pooled paired differences (wm - SFT OOD, rule - SFT IND, wm - rule OOD) over the finished seeds."""
    wm = wm_stem(folder, tag)
    if wm is None:
        return None, None, None, (), None
    seeds = finished_seeds(folder, (wm, RULE, "sft"), tag)
    if not seeds:
        return None, None, None, (), wm
    pooled = lambda stem, base, split: compare(Comparison(stem, stem, base, seeds, tag, (split,)), folder)[split]["pooled"]  # noqa: E731
    return pooled(wm, "sft", "ood"), pooled(RULE, "sft", "ind"), pooled(wm, RULE, "ood"), seeds, wm


def store_facts(store: Path | None) -> tuple[str, dict[str, float | None]]:
    """The store's tag and the precision of every replication rl artifact it holds, by "<stem> s<seed> <split>"."""
    from fresh_state_sweep import policies, store_tag

    from pipeline.errors import PipelineError
    from pipeline.plan import Project, parse_set
    from pipeline.sweep import expand, parse_axes

    try:
        project = Project(ROOT / "pipeline.yaml", store=store)
        points, _ = expand(project, SWEEP, project.profile_name(None), parse_set([]), None, parse_axes([]))
    except PipelineError as e:
        raise SystemExit(f"error: {e}") from None
    pols, _, collect_key = policies(project, SWEEP, points)
    precisions = {}
    for pol in pols:
        if pol.rl is None:
            continue
        metrics = json.loads((pol.rl / "metrics.json").read_text())
        for split in ("ind", "ood"):
            precisions[f"{pol.stem} s{pol.seed} {split}"] = metrics.get(f"imagined/{split}/precision")
    return store_tag(project.store, collect_key), precisions


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tag", default=None, help="the files' store tag (default: the store's, as fresh_state_sweep.py)")
    ap.add_argument("--store", type=Path, default=None, help="store directory (default: the spec's)")
    ap.add_argument("--folder", type=Path, default=FRESH)
    args = ap.parse_args()
    own_tag, precisions = store_facts(args.store)
    tag = args.tag or own_tag
    if tag != own_tag:  # the files come from another build of the store: its rl artifacts are not theirs
        print(f"precision not read: the store's tag is {own_tag}, the files' {tag}")
        precisions = {}
    wm_sft, rule_sft, wm_rule, seeds, wm = differences(args.folder, tag)
    print(f"replication, tag {tag}: world-model arm {wm or '(no files yet)'}; seeds with every file: "
          f"{', '.join(map(str, seeds)) or 'none'} of {', '.join(map(str, SEEDS))}")
    if 0 < len(seeds) < len(SEEDS):
        print(f"  (predictions 1-3 read on {len(seeds)} of {len(SEEDS)} seeds: 'so far', not the pre-registered reading)")
    for r in judge(wm_sft, rule_sft, wm_rule, precisions, seeds):
        verdict = {True: "holds", False: "FAILS", None: "open"}[r.holds]
        if r.name in "123" and r.holds is not None and len(seeds) < len(SEEDS):
            verdict += " so far"
        if r.name == "decision":
            verdict = {True: "MET", False: "NOT MET", None: "pending"}[r.holds]
        print(f"  {r.name:>8}  {verdict:<14} predicted: {r.predicted}; measured: {r.measured}")


if __name__ == "__main__":
    main()
