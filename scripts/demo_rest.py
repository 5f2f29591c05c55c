"""How often the demonstrations, as the sft stage reads them, command rest.

The evaluate stage counts an episode as "came to rest" when the policy commanded a TCP displacement
below ``REST_ACTION`` for ``REST_STEPS`` policy steps running (stages/evaluate/episodes.py). This
script applies the same measure to the demonstrations SFT imitates (``stages.sft.data.load_demo``,
with the sft stage's frame skip and re-timing), per task: the share of policy steps at rest, how
many demonstrations contain such a run, and the longest run. A policy that rests where its
demonstrations never do has not copied a rest; it has reached a state they do not continue from.

    PYTHONPATH=. .venv/bin/python scripts/demo_rest.py COLLECT TOKENIZE [--kinds optimal] [--frame-skip 4]
        [--min-move 0.03] [--max-gap 12] [--all-episodes]

By default only the episodes of the tokenize split's training pool are read (those SFT may train on).
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from stages.evaluate.episodes import REST_ACTION, REST_STEPS, longest_rest
from stages.sft.data import load_demo


def demo_rest(ds, store, episode_ids, frame_skip: int, min_move: float, max_gap: int) -> dict:
    """Per task: {"episodes", "steps", "rest_steps", "rested" (episodes with a run >= REST_STEPS), "longest"}."""
    task = {m.episode_id: m.task for m in ds.episodes}
    out: dict = defaultdict(lambda: {"episodes": 0, "steps": 0, "rest_steps": 0, "rested": 0, "longest": 0})
    for i in episode_ids:
        d = load_demo(ds, store, i, frame_skip, min_move, max(max_gap, frame_skip))
        pos = d.actions[:, :3]  # (T', 3) commanded TCP displacement per policy step
        run = longest_rest(pos)
        row = out[task[i]]
        row["episodes"] += 1
        row["steps"] += len(pos)
        row["rest_steps"] += int((np.linalg.norm(pos, axis=1) < REST_ACTION).sum())
        row["rested"] += int(run >= REST_STEPS)
        row["longest"] = max(row["longest"], run)
    return dict(sorted(out.items()))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("collect", type=Path)
    p.add_argument("tokenize", type=Path)
    p.add_argument("--kinds", nargs="+", default=["optimal"], help="episode kinds read (collect's `kind`)")
    p.add_argument("--frame-skip", type=int, default=4, help="sft.frame_skip")
    p.add_argument("--min-move", type=float, default=0.03, help="sft.retime_min_move")
    p.add_argument("--max-gap", type=int, default=12, help="sft.retime_max_gap")
    p.add_argument("--all-episodes", action="store_true", help="not only the tokenize split's training pool")
    a = p.parse_args(argv)
    from stages.collect.dataset import Dataset
    from stages.tokenize.store import TokenStore
    ds, store = Dataset(a.collect), TokenStore(a.tokenize)
    pool = None if a.all_episodes else set(json.loads((a.tokenize / "split.json").read_text())["train"])
    ids = sorted(m.episode_id for m in ds.episodes
                 if m.success and m.kind in a.kinds and (pool is None or m.episode_id in pool))
    if not ids:
        raise SystemExit(f"no successful episodes of kinds {a.kinds} in {a.collect}")
    rows = demo_rest(ds, store, ids, a.frame_skip, a.min_move, a.max_gap)
    print(f"policy steps commanding |delta position| < {REST_ACTION}; 'rested' = a run of >= {REST_STEPS} such steps")
    print("| task | demonstrations | policy steps | at rest | rested | longest run |")
    print("|---|---|---|---|---|---|")
    for t, r in rows.items():
        print(f"| {t} | {r['episodes']} | {r['steps']} | {r['rest_steps'] / max(r['steps'], 1):.3f} | "
              f"{r['rested']}/{r['episodes']} | {r['longest']} |")


if __name__ == "__main__":
    main()
