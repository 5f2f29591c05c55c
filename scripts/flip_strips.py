"""Look at the fresh states where two policies disagree: frame strips of both, one state per image.

A paired difference of +0.03 is a handful of states where the method succeeds and its baseline fails,
against a slightly smaller handful the other way. Before believing it, look at those states: this
script reads two per-episode files of the same fresh states (``scripts/evaluate_sft.py --out``, e.g. a
replication seed's PPO policy and its SFT policy), picks the states one policy won and the other
lost (``--per-way`` each way, spread over tasks), runs both policies there again in the simulator and
saves, per state, one image with the method's third-view frames above the baseline's.

    PYTHONPATH=. .venv/bin/python scripts/flip_strips.py <collect> <tokenize> <sft> \\
        --method FILE [--method-rl RL_DIR] [--method-sft SFT_DIR] --baseline FILE [--baseline-rl RL_DIR] \\
        [--baseline-sft SFT_DIR] [--seed 1] [--per-way 3] [--same 0] [--out DIR] [--jobs 2]

A file of PPO episodes (its rows' ``policy`` is ``ppo``) needs its rl artifact (``--method-rl`` /
``--baseline-rl``); SFT episodes use the ``sft`` artifact, or the side's own (``--method-sft`` /
``--baseline-sft``) when the two sides are different SFT trainings (e.g. an ensemble and one member). ``--seed`` is the files' evaluate_sft.py
``--seed``. ``--same N`` adds N states both policies won and N both lost (a look at the ordinary).
Every episode is run again from its own seed (every reset rebuilds the scene), so the rerun's outcome
should be the file's: the script prints how many reproduced and names any that did not.
Writes ``DIR/<gained|lost|both_won|both_lost>_<task>_<split>_<scene>_<seed>.png`` and ``DIR/index.md``.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from fresh_state_table import episodes  # noqa: E402

KINDS = ("gained", "lost", "both_won", "both_lost")  # the method's outcome against the baseline's on a state


def state(row: dict) -> tuple[str, str, str, int]:
    """(task, split, scene_id, seed): one fresh initial state."""
    return row["task"], row["split"], str(row["scene_id"]), int(row["seed"])


def pick(method: list[dict], baseline: list[dict], per_way: int, same: int) -> dict[str, list[tuple]]:
    """Per kind, up to its count of paired states, taken round-robin over tasks (each task's states in
    file order) so one task does not fill the page."""
    base = {state(r): bool(r["success"]) for r in baseline}
    paired = [(state(r), bool(r["success"]), base[state(r)]) for r in method if state(r) in base]
    if not paired:
        raise SystemExit("the two files share no initial state: are they the same seed's fresh states?")
    kind_of = {(True, False): "gained", (False, True): "lost", (True, True): "both_won", (False, False): "both_lost"}
    wanted = {"gained": per_way, "lost": per_way, "both_won": same, "both_lost": same}
    out = {}
    for kind in KINDS:
        by_task: dict[str, list[tuple]] = {}
        for s, m, b in paired:
            if kind_of[(m, b)] == kind:
                by_task.setdefault(s[0], []).append(s)
        chosen, queues = [], [list(q) for q in by_task.values()]
        while len(chosen) < wanted[kind] and any(queues):
            for q in queues:
                if q and len(chosen) < wanted[kind]:
                    chosen.append(q.pop(0))
        out[kind] = chosen
    return out


def jobs_for(states: list[tuple], label: str, policy_dir: Path | None, sft: Path, args, counts: dict) -> list:
    """The evaluate stage's jobs for one policy (``sft``'s, or ``policy_dir``'s PPO policy), cut down to
    ``states`` (each recorded)."""
    from stages.evaluate import Config
    from stages.evaluate.jobs import build_jobs
    from stages.sft import read_policy_json

    info = read_policy_json(sft)
    dirs = {"collect": args.collect, "tokenize": args.tokenize, "sft": sft, "rl": policy_dir or Path("/nonexistent")}
    ctx = SimpleNamespace(input=lambda name: dirs[name], device="cpu")
    splits = sorted({s[1] for s in states})
    # the files' own plan (episodes per task and split, seed), so every scene the files used has a job
    cfg = Config(episodes=max(counts.values()), seed=args.seed, policies=[label], splits=splits, videos=False,
                 max_steps=args.max_steps, snapshot_episodes=0)
    jobs = build_jobs(ctx, cfg, {"tasks": info["tasks"], "frame_skip": info["frame_skip"]})
    wanted: dict[tuple, list[int]] = {}
    for task, split, scene, seed in states:
        wanted.setdefault((task, split, scene), []).append(seed)
    out = []
    for job in jobs:
        seeds = wanted.pop((job.task, job.split, str(job.scene["scene_id"])), None)
        if seeds:
            job.seeds, job.record = seeds, list(seeds)
            out.append(job)
    if wanted:
        raise SystemExit(f"no scene of the evaluate plan (seed {args.seed}) matches {sorted(wanted)}: "
                         "is --seed the files' evaluate_sft.py --seed?")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in ("collect", "tokenize", "sft"):
        ap.add_argument(name, type=Path)
    ap.add_argument("--method", type=Path, required=True, help="the method's per-episode file")
    ap.add_argument("--method-rl", type=Path, default=None, help="its rl artifact (when its episodes are PPO's)")
    ap.add_argument("--method-sft", type=Path, default=None, help="its own sft artifact (default: the positional one)")
    ap.add_argument("--baseline", type=Path, required=True, help="the baseline's per-episode file")
    ap.add_argument("--baseline-rl", type=Path, default=None, help="its rl artifact (when its episodes are PPO's)")
    ap.add_argument("--baseline-sft", type=Path, default=None, help="its own sft artifact (default: the positional one)")
    ap.add_argument("--seed", type=int, default=1, help="the files' evaluate_sft.py --seed")
    ap.add_argument("--per-way", type=int, default=3, help="states the method gained, and as many it lost")
    ap.add_argument("--same", type=int, default=0, help="also this many states both won and both lost")
    ap.add_argument("--frames", type=int, default=10, help="frames per strip, start to end")
    ap.add_argument("--max-steps", type=int, default=75)
    ap.add_argument("--out", type=Path, default=Path("flip_strips"))
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    if min(args.per_way, args.same) < 0 or args.frames < 2:
        raise SystemExit("--per-way and --same must be >= 0, --frames >= 2")

    sides = {}
    for side, path, rl, sft in (("method", args.method, args.method_rl, args.method_sft),
                                ("baseline", args.baseline, args.baseline_rl, args.baseline_sft)):
        rows = episodes(path)
        label = rows[0]["policy"]
        if label not in ("sft", "ppo"):
            raise SystemExit(f"{path}: policy {label!r}: this script reruns 'sft' or 'ppo' episodes")
        if label == "ppo" and rl is None:
            raise SystemExit(f"{path} holds PPO episodes: give its rl artifact (--{side}-rl)")
        counts: dict[tuple, int] = {}
        for r in rows:
            counts[(r["task"], r["split"])] = counts.get((r["task"], r["split"]), 0) + 1
        sides[side] = SimpleNamespace(path=path, rows=rows, label=label, rl=rl if label == "ppo" else None,
                                      sft=sft or args.sft, counts=counts)
    chosen = pick(sides["method"].rows, sides["baseline"].rows, args.per_way, args.same)
    states = [s for kind in KINDS for s in chosen[kind]]
    from stages.rl import read_rl_facts

    for s in sides.values():  # evaluate_sft.py files every rl policy as "ppo": title it by the rl stage's method
        s.title = s.label if s.rl is None else read_rl_facts(s.rl)["method"]
    print(", ".join(f"{kind} {len(chosen[kind])}" for kind in KINDS) + f" states of {args.method.name} vs {args.baseline.name}")
    if not states:
        print("nothing to show")
        return

    from stages.evaluate.episodes import run_job

    jobs = {side: jobs_for(states, s.label, s.rl, s.sft, args, s.counts) for side, s in sides.items()}
    rerun: dict[tuple, dict] = {}
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        for side in sides:
            for results in pool.imap_unordered(run_job, jobs[side]):
                for r in results:
                    rerun[(side, state(r))] = r
    write(args, sides, chosen, rerun)


def write(args, sides: dict, chosen: dict, rerun: dict) -> None:
    """The images, index.md, and the reproduction check."""
    import numpy as np

    from stages.evaluate.report import strip_figure

    args.out.mkdir(parents=True, exist_ok=True)
    filed = {side: {state(r): bool(r["success"]) for r in s.rows} for side, s in sides.items()}
    mismatches, checked = [], 0
    lines = [f"# {args.method.name} (above) vs {args.baseline.name} (below)", ""]
    mark = {True: "success", False: "fail"}
    for kind in KINDS:
        if not chosen[kind]:
            continue
        lines += [f"## {kind.replace('_', ' ')}", ""]
        for s in chosen[kind]:
            rows = []
            for side in sides:
                r = rerun[(side, s)]
                checked += 1
                if bool(r["success"]) != filed[side][s]:
                    mismatches.append(f"{side} {s}: file {mark[filed[side][s]]}, rerun {mark[bool(r['success'])]}")
                frames = r["frames"]  # (control steps+1, H, W, 3) uint8
                picks = np.linspace(0, len(frames) - 1, args.frames).round().astype(int)
                rows.append((f"{side} ({sides[side].title}): {mark[bool(r['success'])]} in {r['steps']} steps", frames[picks]))
            task, split, scene, seed = s
            name = f"{kind}_{task}_{split}_{scene}_{seed}.png"
            strip_figure(rows, args.out / name, f"{task}, {split}, scene {scene}, seed {seed}")
            lines.append(f"![{kind} {task} {split} {scene} {seed}]({name})")
        lines.append("")
    reproduced = checked - len(mismatches)
    lines.append(f"Outcomes reproduced by the rerun: {reproduced} of {checked}.")
    lines += [f"- not reproduced: {m}" for m in mismatches]
    (args.out / "index.md").write_text("\n".join(lines) + "\n")
    print(f"outcomes reproduced by the rerun: {reproduced} of {checked}")
    for m in mismatches:
        print(f"  NOT reproduced: {m}")
    print(f"strips in {args.out} (index.md)")


if __name__ == "__main__":
    main()
