"""Success of an sft artifact's policy in the simulator, without PPO: the evaluate stage's own jobs
(same scenes, same initial states, same success check), for iterating on SFT quickly.

    PYTHONPATH=. .venv/bin/python scripts/evaluate_sft.py <collect> <tokenize> <sft> [--episodes 25] [--jobs 2]

``--seed 1`` draws initial states disjoint from the evaluate stage's (its ``seed`` 0).
``--rl <rl artifact>`` evaluates that artifact's PPO policy (``policy.zip``) instead, on the same
initial states; ``scripts/paired_success.py`` then pairs it with the SFT episodes.

Prints success per (task, split) and pooled, with Wilson 95% intervals, and writes the per-episode
results next to nothing else (``--out results.jsonl`` to keep them). With ``--out F`` every finished
job's episodes are appended to ``F.partial`` at once, and the same command after a kill runs only the
jobs that file lacks (it says how many it kept); ``F`` is written when every job is done and the
partial file is removed. A worker reuses its simulator across jobs, but every reset rebuilds the
scene (``stages.common.sim_env``), so a resumed run's episodes are those an uninterrupted run gives
(before 2026-12-05 they could differ: an episode depended on what its worker simulated before it).
``--strips DIR`` also saves,
for the first episode of each (task, split), a strip of 8 third-view frames from start to end
(``DIR/<split>_<task>_<success|fail>.png``): look at what the policy does before believing a rate.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo root: runs without PYTHONPATH=.


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in ("collect", "tokenize", "sft"):
        ap.add_argument(name, type=Path)
    ap.add_argument("--episodes", type=int, default=25, help="episodes per (task, split)")
    ap.add_argument("--seed", type=int, default=0, help="the evaluate stage's seed: another value draws initial "
                    "states disjoint from the stage's default ones (a fresh sample, e.g. to replicate a result)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--splits", default="ind,ood")
    ap.add_argument("--max-steps", type=int, default=75)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--rl", type=Path, default=None, help="evaluate this rl artifact's PPO policy instead of SFT "
                    "(a directory), or one of its snapshots (a .zip under snapshots/)")
    ap.add_argument("--strips", type=Path, default=None, help="save a frame strip of one episode per (task, split) here")
    args = ap.parse_args()

    from stages.evaluate import Config
    from stages.evaluate.jobs import build_jobs
    from stages.evaluate.episodes import run_job
    from stages.evaluate.stats import fmt_rate
    from stages.sft import read_policy_json

    info = read_policy_json(args.sft)
    rl_dir = args.rl or Path("/nonexistent")
    snapshot = None
    if args.rl is not None and args.rl.suffix == ".zip":  # a snapshot: the jobs read <dir>/policy.zip
        snapshot = tempfile.TemporaryDirectory(prefix="evaluate_snapshot_")
        rl_dir = Path(snapshot.name)
        (rl_dir / "policy.zip").symlink_to(args.rl.resolve())
    dirs = {"collect": args.collect, "tokenize": args.tokenize, "sft": args.sft, "rl": rl_dir}
    ctx = SimpleNamespace(input=lambda name: dirs[name], device="cpu")
    cfg = Config(episodes=args.episodes, seed=args.seed, policies=["ppo" if args.rl else "sft"], splits=args.splits.split(","), videos=False,
                 max_steps=args.max_steps, snapshot_episodes=0)
    jobs = build_jobs(ctx, cfg, {"tasks": info["tasks"], "frame_skip": info["frame_skip"]})
    if args.strips is not None:
        first = {}
        for job in jobs:
            first.setdefault((job.task, job.split), job)
        for job in first.values():
            job.record = [job.seeds[0]]
    partial = args.out.with_name(args.out.name + ".partial") if args.out is not None else None
    kept = read_partial(partial, jobs) if partial is not None else []
    todo = pending(jobs, kept)
    if kept:
        print(f"resuming: {len(jobs) - len(todo)} of {len(jobs)} jobs ({len(kept)} episodes) kept from {partial}; "
              f"running {len(todo)}" + (" (frame strips only for those)" if args.strips is not None else ""))
    t0 = time.perf_counter()
    results = list(kept)
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        for rs in pool.imap_unordered(run_job, todo):
            results.extend(rs)
            if partial is not None:
                append_rows(partial, [_row(r) for r in rs])
    seconds = time.perf_counter() - t0
    if snapshot is not None:
        snapshot.cleanup()
    if args.strips is not None:
        _save_strips(results, args.strips)
    results = [_row(r) for r in results]
    if args.out is not None:
        tmp = args.out.with_name(args.out.name + ".tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in results))
        tmp.replace(args.out)
        partial.unlink(missing_ok=True)
    print(f"{len(results)} episodes in {seconds:.0f} s ({args.jobs} workers)")
    for split in cfg.splits:
        cells = []
        for task in [*info["tasks"], "all"]:
            rs = [r for r in results if r["split"] == split and (task == "all" or r["task"] == task)]
            cells.append(f"{task} {fmt_rate(sum(r['success'] for r in rs), len(rs))}")
        print(f"{split}: " + " | ".join(cells))


def _row(result: dict) -> dict:
    """A result without its frames: what the jsonl files keep."""
    return {k: v for k, v in result.items() if k != "frames"}


def _episode(row: dict) -> tuple:
    return row["policy"], row["task"], row["scene_id"], row["split"], int(row["seed"])


def _job_episodes(job) -> set[tuple]:
    return {(job.policy, job.task, job.scene["scene_id"], job.split, int(s)) for s in job.seeds}


def read_partial(path: Path, jobs: list) -> list[dict]:
    """The rows of ``path`` that belong to a job whose every episode is there (a kill can tear the last
    line or leave a job half written); the file is rewritten with those rows only, so appends follow a
    whole line."""
    if not path.exists():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue  # a torn line
    have = {_episode(r) for r in rows}
    complete = set().union(*(_job_episodes(j) for j in jobs if _job_episodes(j) <= have)) if jobs else set()
    kept = [r for r in rows if _episode(r) in complete]
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("".join(json.dumps(r) + "\n" for r in kept))
    tmp.replace(path)
    return kept


def pending(jobs: list, kept: list[dict]) -> list:
    """The jobs with an episode not in ``kept``."""
    have = {_episode(r) for r in kept}
    return [j for j in jobs if not _job_episodes(j) <= have]


def append_rows(path: Path, rows: list[dict]) -> None:
    """Append one job's rows in one write, on disk before the next job's."""
    with open(path, "a") as f:
        f.write("".join(json.dumps(r) + "\n" for r in rows))
        f.flush()
        os.fsync(f.fileno())


def _save_strips(results: list[dict], out: Path) -> None:
    import numpy as np
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    for r in results:
        if "frames" not in r:
            continue
        frames = r["frames"]  # (control steps+1, H, W, 3) uint8
        picks = np.linspace(0, len(frames) - 1, 8).round().astype(int)
        strip = np.concatenate([frames[i] for i in picks], axis=1)  # (H, 8W, 3)
        name = f"{r['split']}_{r['task']}_{'success' if r['success'] else 'fail'}.png"
        Image.fromarray(strip).resize((strip.shape[1] * 2, strip.shape[0] * 2), Image.NEAREST).save(out / name)
    print(f"frame strips in {out}")


if __name__ == "__main__":
    main()
