"""Which dense term tracks progress? The `wm` reward's LPIPS to the goal per camera, and read
against the episode's start.

The rl stage's reward diagnostics (``stages.rl.train._diagnose``) score the dense term (with
``dense: similarity``, 1 - LPIPS to the environment's goal frame averaged over the third view and the
wrist view) along held-out
successful episodes (frames through the tokenizer, as the world model's frames are) and report its
Spearman correlation with progress t / T. This probe does the same on more episodes and reads the
two views apart: third view alone, wrist view alone, and their mean (the reward as it is), per
split and per task, with a bootstrap interval over episodes; and the mean correlation of a weighted
mean of the two views' distances for a few wrist weights, on IND *training* episodes too (choose a
weight there, read it on the held-out and OOD ones). It also scores the terms that read the distance
to the episode's first frame (``relative``: ``diff``, which is ``dense: progress``, the ``ratio``, and
that distance alone), paired with the goal-only term, and how episodes end: each term's AUROC at the
last frame, successful episodes against collect's near-miss and grasp-miss failures.

    PYTHONPATH=. .venv/bin/python scripts/dense_view_probe.py <collect> <tokenize> <train_wm> <sft> <goals> \\
        [--episodes 64] [--seed 0] [--out F.json]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

VIEWS = ("third", "wrist", "both")
RELATIVE = ("ratio", "diff", "start")  # relative(): the distance to the start read too (start: it alone)
WRIST_WEIGHTS = (0.0, 0.25, 0.5, 0.625, 0.75, 0.875, 1.0)  # dense = 1 - ((1 - w) LPIPS_third + w LPIPS_wrist)


def weighted(d: dict[str, np.ndarray], w: float) -> np.ndarray:
    return (1 - w) * d["third"] + w * d["wrist"]


def view_correlations(d: dict[str, np.ndarray]) -> dict[str, float]:
    """Spearman of the dense term (1 - LPIPS) with progress t / T for frames 1..T of one episode, per
    view (``VIEWS``) and per wrist weight (keys ``w<weight>``); NaN where the distance never changes
    or the episode has under 3 frames (as the rl stage's diagnostics skip them)."""
    from stages.rl.diagnostics import progress_correlation  # the rl stage's own reading, one episode here

    t = len(d["both"])
    progress, episode = np.arange(1, t + 1) / t, np.zeros(t, dtype=int)
    series = {**{v: d[v] for v in VIEWS}, **{f"w{w:g}": weighted(d, w) for w in WRIST_WEIGHTS}}
    out = {k: progress_correlation(1.0 - x, progress, episode) for k, x in series.items()}
    for k, x in relative(d).items():
        out[k] = progress_correlation(x, progress, episode)
    return out


def relative(d: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Dense terms that also read the distance to the episode's start (higher = further along)."""
    s, g = d["start"], d["both"]
    return {"ratio": s / np.maximum(s + g, 1e-8), "diff": s - g, "start": s}


def episode_distances(inp, distance, episode_id: str) -> dict[str, np.ndarray]:
    """LPIPS (T,) of frames 1..T of one episode to its environment's goal, per view and their mean;
    ``start``: both views' mean LPIPS of frames 1..T to the episode's first frame."""
    tokens = torch.as_tensor(inp.tokens(episode_id))  # (T+1, h, w)
    third, wrist = inp.tok.decode(tokens)  # (T+1, 3, H, W) x 2 in [0, 1]
    row = torch.full((len(tokens) - 1,), inp.env_of(episode_id), dtype=torch.long)
    net = distance.net
    per_view, to_start = [], []
    for f, gf in zip(distance.features(third, wrist), distance.goal_feats):
        now, first = [x[1:] for x in f], [x[:1].expand_as(x[1:]) for x in f]
        per_view.append(net.distance_from_features(now, [g[row] for g in gf]).cpu().numpy())  # (T,)
        to_start.append(net.distance_from_features(now, first).cpu().numpy())  # (T,)
    return {"third": per_view[0], "wrist": per_view[1], "both": (per_view[0] + per_view[1]) / 2,
            "start": (to_start[0] + to_start[1]) / 2}


def bootstrap(values: np.ndarray, rng, n: int = 2000) -> tuple[float, float]:
    means = [values[rng.integers(0, len(values), len(values))].mean() for _ in range(n)]
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in ("collect", "tokenize", "train_wm", "sft", "goals"):
        ap.add_argument(name, type=Path, help=f"a committed {name} artifact directory")
    ap.add_argument("--episodes", type=int, default=64, help="successful episodes per split (a seeded choice)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="write the per-episode correlations here (JSON)")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.rl.rewards import GoalDistance

    inp = _load({n: getattr(args, n) for n in ("collect", "tokenize", "train_wm", "sft", "goals")})
    distance = GoalDistance(*inp.goal_frames())
    rng = np.random.default_rng(args.seed)
    report: dict = {"goal_mode": inp.goals["goal_mode"], "splits": {}}
    for split, ids in (("train", inp.split["train"]), ("ind", inp.split["heldout"]), ("ood", inp.split["ood"])):
        pick = inp.episodes_for(ids, inp.tasks, True, args.episodes, args.seed)
        rows = []
        for eid in pick:
            d = episode_distances(inp, distance, eid)
            row = {"episode": eid, "task": inp.meta[eid].task, "frames": len(d["both"]), **view_correlations(d)}
            rows.append(row)
        out = {"episodes": len(rows), "views": {}, "tasks": {}}
        for v in VIEWS + RELATIVE:
            vals = np.array([r[v] for r in rows if np.isfinite(r[v])])
            lo, hi = bootstrap(vals, rng)
            out["views"][v] = {"spearman": float(vals.mean()), "lo": lo, "hi": hi}
        out["wrist_weights"] = {f"{w:g}": float(np.nanmean([r[f"w{w:g}"] for r in rows])) for w in WRIST_WEIGHTS}
        for task in sorted({r["task"] for r in rows}):
            rs = [r for r in rows if r["task"] == task]
            out["tasks"][task] = {"episodes": len(rs), **{v: float(np.nanmean([r[v] for r in rs])) for v in VIEWS + RELATIVE}}
        if split == "train":  # the weight a researcher would pick, on training episodes only
            report["chosen_wrist_weight"] = max(WRIST_WEIGHTS, key=lambda w: out["wrist_weights"][f"{w:g}"])
        else:  # what it gains over the reward as it is, paired over the same episodes
            w = report["chosen_wrist_weight"]
            diff = np.array([r[f"w{w:g}"] - r["both"] for r in rows if np.isfinite(r[f"w{w:g}"]) and np.isfinite(r["both"])])
            lo, hi = bootstrap(diff, rng)
            out["chosen_minus_both"] = {"weight": w, "mean": float(diff.mean()), "lo": lo, "hi": hi}
            for k in RELATIVE:  # the start-relative terms, paired with the reward as it is
                diff = np.array([r[k] - r["both"] for r in rows if np.isfinite(r[k]) and np.isfinite(r["both"])])
                lo, hi = bootstrap(diff, rng)
                out[f"{k}_minus_both"] = {"mean": float(diff.mean()), "lo": lo, "hi": hi}
        report["splits"][split] = {**out, "rows": rows}
        print(f"{split} ({len(rows)} episodes): " + ", ".join(
            f"{v} {out['views'][v]['spearman']:.3f} [{out['views'][v]['lo']:.3f}, {out['views'][v]['hi']:.3f}]" for v in VIEWS + RELATIVE))
        print("  wrist weight: " + " ".join(f"{w} {v:.3f}" for w, v in out["wrist_weights"].items()))
        if "chosen_minus_both" in out:
            c = out["chosen_minus_both"]
            print(f"  wrist weight {c['weight']:g} (chosen on train) minus both views' mean: {c['mean']:+.3f} [{c['lo']:+.3f}, {c['hi']:+.3f}]")
            for k in RELATIVE:
                c = out[f"{k}_minus_both"]
                print(f"  {k} minus both views' mean: {c['mean']:+.3f} [{c['lo']:+.3f}, {c['hi']:+.3f}]")
        for task, t in out["tasks"].items():
            print(f"  {task:12s} n={t['episodes']:3d} " + " ".join(f"{v} {t[v]:+.3f}" for v in VIEWS + RELATIVE))
    report["ends"] = episode_ends(inp, distance, args.episodes, args.seed)
    if args.out is not None:
        args.out.write_text(json.dumps(report, indent=1) + "\n")


def episode_ends(inp, distance, limit: int, seed: int) -> dict:
    """Does a dense term separate how successful and failed episodes end? AUROC (success vs the collect's
    labelled failures, near-miss and grasp-miss) of each term at the episode's last frame, per split;
    a term that pays for mere change from the start would not."""
    from stages.collect.plans import FAILURE_KINDS
    from stages.train_wm.evaluate import auroc

    out = {}
    for split, ids in (("ind", inp.split["heldout"]), ("ood", inp.split["ood"])):
        good = inp.episodes_for(ids, inp.tasks, True, limit, seed)
        bad = inp.episodes_for(ids, inp.tasks, False, limit, seed, kinds=list(FAILURE_KINDS))
        last = {k: [] for k in VIEWS + RELATIVE}
        for eid in good + bad:
            d = episode_distances(inp, distance, eid)
            terms = {**{v: 1.0 - d[v] for v in VIEWS}, **relative(d)}
            for k, x in terms.items():
                last[k].append(x[-1])
        label = np.array([1] * len(good) + [0] * len(bad))
        out[split] = {"successes": len(good), "failures": len(bad),
                      "auroc": {k: auroc(np.array(v), label) for k, v in last.items()}}
        print(f"{split} ends ({len(good)} successes, {len(bad)} failures), AUROC of the last frame's term: "
              + " ".join(f"{k} {a:.3f}" for k, a in out[split]["auroc"].items()))
    return out


def _load(dirs: dict):
    """RLInputs without a world model (this probe steps none), with train_wm's split and the goals."""
    from stages.goals import load_goals
    from stages.rl import Config
    from stages.rl.inputs import RLInputs

    ctx = SimpleNamespace(input=lambda name: dirs[name], device="cpu")
    inp = RLInputs.load(ctx, Config(reward="rule", diagnostics="none", precision_envs=0))
    inp.split = json.loads((dirs["train_wm"] / "split.json").read_text())
    inp.goals = load_goals(dirs["goals"])
    inp.goal_index = {env_id: i for i, env_id in enumerate(inp.goals["env_ids"])}
    return inp


if __name__ == "__main__":
    main()
