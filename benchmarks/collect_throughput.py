"""Collection throughput at 64x64 with two camera views, for 1 and 2 worker processes.

    .venv/bin/python benchmarks/collect_throughput.py [--scenes 2] [--per-scene 2] [--workers 1 2]

Prints trajectories/min and frames/s (env steps; each step renders both views), the planner
success rate per task and the open-loop replay success rate per task (every successful optimal
episode is replayed under pd_ee_delta_pose). Simulator start-up (one env per task per worker) is
timed separately and excluded from the rates.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages.collect import Config, plan_jobs, scene_catalog  # noqa: E402
from stages.collect.tasks import TASKS  # noqa: E402


def _warm_up(args) -> float:
    image_size, robot_mesh = args
    import torch

    torch.set_num_threads(1)
    from stages.collect.worker import _sim

    t0 = time.perf_counter()
    for task in TASKS:
        _sim(task, image_size, robot_mesh, 400)
    return time.perf_counter() - t0


def _init(image_size: int, robot_mesh: str) -> None:
    _warm_up((image_size, robot_mesh))


def _collect(job):
    from stages.collect.worker import collect_shard

    return collect_shard(job)


def bench(workers: int, cfg: Config, out: Path) -> dict:
    shard_dir = out / "shards"
    shard_dir.mkdir(parents=True)
    jobs = plan_jobs(cfg, scene_catalog(cfg), shard_dir)
    ctx = mp.get_context("spawn")
    t0 = time.perf_counter()
    with ctx.Pool(workers, initializer=_init, initargs=(cfg.image_size, cfg.robot_mesh)) as pool:
        pool.map(_warm_up, [(cfg.image_size, cfg.robot_mesh)] * workers, chunksize=1)  # wait for every initializer
        t1 = time.perf_counter()
        results = pool.map(_collect, jobs, chunksize=1)
        t2 = time.perf_counter()
    per_task = {}
    for task in cfg.tasks:
        st = [r["stats"] for r in results if r["task"] == task]
        per_task[task] = {k: sum(s[k] for s in st) for k in st[0]}
    total = {k: sum(p[k] for p in per_task.values()) for k in next(iter(per_task.values()))}
    return dict(workers=workers, startup_s=t1 - t0, seconds=t2 - t1, per_task=per_task, total=total)


def _pct(num, den) -> str:
    return "n/a" if den == 0 else f"{100 * num / den:.0f}% ({num}/{den})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=2, help="IND scenes per task")
    ap.add_argument("--per-scene", type=int, default=2, help="optimal trajectories per scene and task (plus as many suboptimal)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--image-size", type=int, default=64)
    ap.add_argument("--robot-mesh", default="lowpoly", choices=["lowpoly", "stock"])
    args = ap.parse_args()
    cfg = Config(ind_scenes=args.scenes, ood_scenes=0, optimal_per_scene=args.per_scene, suboptimal_ratio=1.0,
                 replay_fraction=1.0, episodes_per_shard=2, image_size=args.image_size, robot_mesh=args.robot_mesh)
    print(f"collect throughput: {args.image_size}x{args.image_size}, two views, robot_mesh={args.robot_mesh}, "
          f"{args.scenes} scenes x {2 * args.per_scene} trajectories per task, cpus={os.cpu_count()}, load={os.getloadavg()[0]:.2f}")
    for w in args.workers:
        with tempfile.TemporaryDirectory() as tmp:
            r = bench(w, cfg, Path(tmp))
        t = r["total"]
        print(f"\nworkers={w}: startup {r['startup_s']:.1f} s (excluded); {t['written']} trajectories, {t['frames']} frames in {r['seconds']:.1f} s")
        # replays run inside the workers; remove their share of the wall time for the collection rate
        collect_s = r["seconds"] - t["replay_seconds"] / w
        print(f"  trajectories/min: {60 * t['written'] / collect_s:.1f}   frames/s: {t['frames'] / collect_s:.1f} "
              f"(x2 views = {2 * t['frames'] / collect_s:.1f} images/s); replay verification took {t['replay_seconds']:.1f} worker-s more")
        for task, s in r["per_task"].items():
            print(f"  {task:12s} planner success {_pct(s['attempts'] - s['plan_failures'], s['attempts'])}, "
                  f"execution success {_pct(s['attempts'] - s['plan_failures'] - s['exec_failures'], s['attempts'] - s['plan_failures'])}, "
                  f"replay success {_pct(s['replay_success'], s['replayed'])}")


if __name__ == "__main__":
    main()
