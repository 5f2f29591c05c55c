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

    PYTHONPATH=. .venv/bin/python scripts/replication_verdict.py [--store DIR] [--folder F]

It reads the seeds whose three policies (`sft`, the `wm` arm, `rule`) have finished files in both splits;
with fewer than six, the predictions are read on those seeds and the decision is "pending". The store
did not outlive its machine, so the seeds may come from several builds of it (the amendment in
docs/RESULTS.md, "Target 2's replication survives a new machine", written down before any seed of
a second build was read): each seed counts with the files of one build (its tag in the file names; the
build it finished on first), paired within that build, and the pooled reading spans the builds.
Precision is recorded in ``replication_precision.json`` beside the episode files, so it outlives the
store: each run merges in the points of the replication's rl artifacts the store holds (tagged with
the store's build), and prediction 4 is read over every recorded point.
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
PRECISION_FILE = "replication_precision.json"  # beside the episode files: precision outlives the store
FILE = re.compile(rf"^(?P<stem>{SWEEP}-.+?)(_ood)?_s\d+_(?P<tag>[^_]+)_[^_]+\.jsonl$")  # a replication episode file


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


def wm_stem(folder: Path) -> str | None:
    """The world-model arm's stem: the one `replication-*` stem in the files other than `rule`'s."""
    stems = {m["stem"] for p in folder.iterdir() if (m := FILE.match(p.name))} - {RULE}
    if len(stems) > 1:
        raise SystemExit(f"{folder}: several world-model arms: {sorted(stems)}")
    return next(iter(stems), None)


def seed_tags(folder: Path, stems: tuple[str, ...]) -> dict[int, str]:
    """Each pre-registered seed whose files of every stem exist in both splits under one store's tag: that
    tag. A seed finished on several builds counts on the one it finished on first (the latest date of
    its files); two builds finished on the same day are refused by name."""
    tags = sorted({m["tag"] for p in folder.iterdir() if (m := FILE.match(p.name))})
    out = {}
    for seed in SEEDS:
        done = []
        for tag in tags:
            files = [dated(folder, file_prefix(stem, seed, split, tag)) for stem in stems for split in ("ind", "ood")]
            if all(len(f) == 1 for f in files):
                done.append((max(f[0].name.rsplit("_", 1)[1] for f in files), tag))
        done.sort()
        if len(done) > 1 and done[0][0] == done[1][0]:
            raise SystemExit(f"{folder}: seed {seed} finished on two builds of the store the same day "
                             f"({done[0][1]}, {done[1][1]}): keep one build's files")
        if done:
            out[seed] = done[0][1]
    return out


def differences(folder: Path) -> tuple[dict | None, dict | None, dict | None, dict[int, str], str | None]:
    """Pooled paired differences (wm - SFT OOD, rule - SFT IND, wm - rule OOD) over the finished seeds, each
    seed paired within its own build's files; and the seeds' tags."""
    wm = wm_stem(folder)
    if wm is None:
        return None, None, None, {}, None
    tags = seed_tags(folder, (wm, RULE, "sft"))
    if not tags:
        return None, None, None, {}, wm
    seeds = tuple(sorted(tags))
    per_seed = tuple(tags[s] for s in seeds)
    pooled = lambda stem, base, split: compare(Comparison(stem, stem, base, seeds, per_seed, (split,)), folder)[split]["pooled"]  # noqa: E731
    return pooled(wm, "sft", "ood"), pooled(RULE, "sft", "ind"), pooled(wm, RULE, "ood"), tags, wm


def store_points(store: Path | None) -> tuple[str, list[dict]]:
    """The store's tag and the imagined-success precision of every replication rl artifact it holds, one
    point per (policy, split): {tag, stem, seed, split, precision, imagined_done, imagined_and_replayed}."""
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
    tag = store_tag(project.store, collect_key)
    out = []
    for pol in pols:
        if pol.rl is None:
            continue
        metrics = json.loads((pol.rl / "metrics.json").read_text())
        for split in ("ind", "ood"):
            out.append({"tag": tag, "stem": pol.stem, "seed": pol.seed, "split": split,
                        **{k: metrics.get(f"imagined/{split}/{k}") for k in ("precision", "imagined_done", "imagined_and_replayed")}})
    return tag, out


def record(folder: Path, points: list[dict]) -> list[dict]:
    """Every point of ``folder``'s precision file with ``points`` merged in (a point of the same tag, stem,
    seed and split replaced); the file is rewritten when that changes it. The file keeps precision once
    the store that measured it is gone, as the episode files keep success."""
    path = folder / PRECISION_FILE
    known = json.loads(path.read_text())["points"] if path.is_file() else []
    ident = lambda p: (p["tag"], p["stem"], p["seed"], p["split"])  # noqa: E731
    merged = {ident(p): p for p in known}
    merged.update({ident(p): p for p in points})
    out = sorted(merged.values(), key=ident)
    if out != known:
        path.write_text(json.dumps({"points": out}, indent=1) + "\n")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--store", type=Path, default=None, help="store directory (default: the spec's)")
    ap.add_argument("--folder", type=Path, default=FRESH)
    args = ap.parse_args()
    own_tag, points = store_points(args.store)
    points = record(args.folder, points)
    precisions = {f"{p['stem']} s{p['seed']} {p['tag']} {p['split']}": p["precision"] for p in points}
    wm_sft, rule_sft, wm_rule, tags, wm = differences(args.folder)
    seeds = tuple(sorted(tags))
    print(f"replication: world-model arm {wm or '(no files yet)'}; this store's tag {own_tag}; seeds with every file: "
          f"{', '.join(f'{s} ({tags[s]})' for s in seeds) or 'none'} of {', '.join(map(str, SEEDS))}")
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
