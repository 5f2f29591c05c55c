"""Fresh-state episodes for every policy of a sweep: each seed's SFT policy and each point's PPO policy.

    PYTHONPATH=. .venv/bin/python scripts/fresh_state_sweep.py calibration_gate [--axis PATH=[...]]
        [--profile P] [--set STAGE.KEY=VALUE] [--store DIR] [--tag TAG] [--episodes 100] [--seed 1]
        [--max-steps 75] [--splits ood,ind] [--jobs 2] [--follow SECONDS] [--dry-run]

``--axis``, ``--profile``, ``--set`` and ``--store`` mean what they mean to ``python -m pipeline sweep``:
pass the ones the sweep ran with, so the same points (keys) are found.

For every point of the sweep whose rl artifact the store holds, and for the SFT artifact each point
reads, it runs ``scripts/evaluate_sft.py <collect> <tokenize> <sft> [--rl <rl>] --episodes N --seed S
--out docs/results/fresh_states/<stem>[_ood]_s<seed>_<tag>_<date>.jsonl``, one split at a time and
every policy's first split before any second one (``--splits ood,ind``: the out-of-domain files first).
The stems are ``sft`` and ``<sweep>-<method>`` (the method from the rl artifact's ``rl.json``, e.g.
``calibration_gate-wm_gated``); ``<seed>`` is the point's ``sft.seed``. The tag names the store
(default: ``c`` + the collect key's first 8 characters + 4 hex digits of its collect artifact's manifest,
which differ between two builds of the same key), so files from two stores never pair. Files written
before 2026-12-04 carry the old default, the collect key alone (``cc6f250d4``).

Resumable at two levels: a file that exists is skipped, and a killed evaluation resumes from its
``.partial`` file (``evaluate_sft.py``'s own resume; its date is kept). Points whose rl artifact is
not in the store yet are listed as waiting, so the same command can run after every session's share
of the sweep; ``--follow SECONDS`` instead keeps looking until every point's policy is evaluated, so it can
run beside the sweep itself. At the end it prints the ``comparisons.json`` entries the finished files support, for
``scripts/fresh_state_table.py``.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "scripts"))

from fresh_state_table import FRESH, dated, file_prefix  # noqa: E402  (one naming scheme for writer and reader)


@dataclass(frozen=True)
class Policy:
    stem: str            # file stem: "sft" or "<sweep>-<method>"
    seed: int            # the point's sft.seed: the files' s<seed>
    dirs: tuple          # (collect, tokenize, sft) artifact directories
    rl: Path | None      # the rl artifact (None: the SFT policy itself)


def finished(folder: Path, prefix: str) -> Path | None:
    """The finished episodes file ``<prefix><date>.jsonl``, if there is one."""
    done = dated(folder, prefix)
    if len(done) > 1:
        raise SystemExit(f"{folder}: {len(done)} files match {prefix}<date>.jsonl (expected at most one): "
                         f"{[p.name for p in done]}")
    return done[0] if done else None


def target(folder: Path, prefix: str, today: str) -> tuple[Path, bool]:
    """Where this (policy, split)'s episodes go and whether they are finished: an existing file, else the
    date of an interrupted run's ``.partial`` (so it resumes), else today's."""
    done = finished(folder, prefix)
    if done is not None:
        return done, True
    partial = dated(folder, prefix, ".jsonl.partial")
    date = partial[-1].name[len(prefix):-len(".jsonl.partial")] if partial else today
    return folder / f"{prefix}{date}.jsonl", False


def policies(project, sweep: str, points) -> tuple[list[Policy], list[str], str]:
    """The sweep's policies the store can evaluate now (a seed's SFT policy as soon as its sft artifact is
    committed, a point's PPO policy once its rl artifact is), the labels of points still waiting for
    their rl artifact, and the collect key (the store's identity)."""
    from stages.rl import read_rl_facts

    store = project.store
    out: dict[tuple[str, int], Policy] = {}
    waiting, collect_keys = [], set()

    def committed(node) -> Path | None:
        found = store.lookup(node.stage, node.key)
        return found.path if found.state == "ok" else None

    for pt in points:
        nodes = {n.stage: n for n in pt.nodes}
        missing = [s for s in ("collect", "tokenize", "sft", "rl") if s not in nodes]
        if missing:
            raise SystemExit(f"sweep {sweep!r}: point {pt.label} has no {', '.join(missing)} stage; "
                             "this script needs sweeps that run up to rl or later")
        collect_keys.add(nodes["collect"].key)
        dirs = tuple(committed(nodes[s]) for s in ("collect", "tokenize", "sft"))
        rl_dir = committed(nodes["rl"])
        if rl_dir is None:
            waiting.append(pt.label)
        if None in dirs:
            continue
        seed = int(nodes["sft"].config["seed"])
        prev = out.setdefault(("sft", seed), Policy("sft", seed, dirs, None))
        if prev.dirs != dirs:
            raise SystemExit(f"sweep {sweep!r}: two SFT artifacts share sft.seed {seed} ({prev.dirs[2].name}, "
                             f"{dirs[2].name}); their fresh-state files would collide")
        if rl_dir is None:
            continue
        stem = f"{sweep}-{read_rl_facts(rl_dir)['method']}"
        if (stem, seed) in out:
            raise SystemExit(f"sweep {sweep!r}: two points map to {stem} seed {seed}; give them apart by method")
        out[(stem, seed)] = Policy(stem, seed, dirs, rl_dir)
    if len(collect_keys) > 1:
        raise SystemExit(f"sweep {sweep!r}: its points read {len(collect_keys)} collect artifacts; "
                         "run this once per collect artifact (narrow the sweep with --axis)")
    ordered = sorted(out.values(), key=lambda p: (p.seed, p.stem != "sft", p.stem))
    return ordered, waiting, next(iter(collect_keys), "")


def store_tag(store, collect_key: str) -> str:
    """The default tag: ``c`` + the collect key's first 8 characters + the first 4 hex digits of the
    committed collect artifact's manifest (its file digests, creation time and host), so a store
    rebuilt at the same collect key gets another tag and its policies never pair with the old files."""
    import hashlib

    from pipeline.store import MANIFEST

    found = store.lookup("collect", collect_key)
    if found.state != "ok":
        return f"c{collect_key[:8]}"
    return f"c{collect_key[:8]}{hashlib.sha256((found.path / MANIFEST).read_bytes()).hexdigest()[:4]}"


def command(pol: Policy, split: str, out: Path, args) -> list[str]:
    cmd = [sys.executable, str(ROOT / "scripts" / "evaluate_sft.py"), *map(str, pol.dirs),
           "--episodes", str(args.episodes), "--seed", str(args.seed), "--jobs", str(args.jobs),
           "--max-steps", str(args.max_steps), "--splits", split, "--out", str(out)]
    return cmd + (["--rl", str(pol.rl)] if pol.rl is not None else [])


def drain(plan, run, follow: float, sleep=time.sleep) -> tuple[list[Policy], str]:
    """Evaluate what ``plan`` offers, one (policy, split) at a time, planning again after each so a policy
    that landed meanwhile goes in split order (its out-of-domain file before earlier policies' second
    split). With ``follow`` > 0 it waits that many seconds whenever nothing is left but points still wait
    for their rl artifact; it returns (the last plan's policies, tag) once nothing is left to run or wait for."""
    todo, waiting, pols, tag = plan(True)
    done, last = 0, None
    while True:
        if todo:
            pol, split, out = todo[0]
            if (pol, split, out) == last:
                raise SystemExit(f"{out}: still missing after its evaluation finished; stopping rather than rerunning it")
            last = (pol, split, out)
            done += 1
            print(f"[{done}/{done + len(todo) - 1}] {pol.stem} seed {pol.seed} {split} -> {out.name}", flush=True)
            run(pol, split, out)
        elif waiting and follow > 0:
            print(f"{len(waiting)} point(s) wait for their rl artifact; looking again in {follow:g} s "
                  f"({dt.datetime.now():%H:%M:%S})", flush=True)
            sleep(follow)
        else:
            return pols, tag
        todo, waiting, pols, tag = plan(False)


def manifest_entries(folder: Path, pols: list[Policy], splits: list[str], tag: str) -> list[dict]:
    """One comparisons.json entry per method stem: the seeds whose method and SFT files are both finished."""
    entries = []
    for stem in sorted({p.stem for p in pols if p.stem != "sft"}):
        seeds = sorted(p.seed for p in pols if p.stem == stem and all(
            finished(folder, file_prefix(s, p.seed, sp, tag)) for s in (stem, "sft") for sp in splits))
        if seeds:
            entry = {"label": stem, "stem": stem, "baseline": "sft", "seeds": seeds, "tag": tag}
            if set(splits) != {"ind", "ood"}:
                entry["splits"] = splits
            entries.append(entry)
    return entries


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sweep")
    ap.add_argument("--axis", action="append", default=[], dest="axes", metavar="PATH=[V,...]",
                    help="replace one axis's values, as `pipeline sweep --axis` (repeatable)")
    ap.add_argument("--profile", default=None)
    ap.add_argument("--set", action="append", default=[], dest="sets", metavar="STAGE.KEY=VALUE")
    ap.add_argument("--store", type=Path, default=None, help="store directory (default: the spec's)")
    ap.add_argument("--tag", default=None, help="the store's tag in the file names (default: c + collect key[:8] + "
                    "4 hex digits of the collect artifact's manifest)")
    ap.add_argument("--episodes", type=int, default=100, help="episodes per (task, split)")
    ap.add_argument("--seed", type=int, default=1, help="evaluate_sft.py --seed: 1 draws states apart from the stage's")
    ap.add_argument("--max-steps", type=int, default=75, help="evaluate_sft.py --max-steps")
    ap.add_argument("--splits", default="ood,ind", help="comma-separated, in the order to run them")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--folder", type=Path, default=FRESH)
    ap.add_argument("--dry-run", action="store_true", help="list what would run")
    ap.add_argument("--follow", type=float, default=0, metavar="SECONDS",
                    help="while points wait for their rl artifact (a sweep running beside it), look again every "
                         "SECONDS and evaluate each policy as it lands; 0 (default): evaluate what is there and stop")
    args = ap.parse_args()
    splits = [s.strip() for s in args.splits.split(",") if s.strip()]
    if not splits or not set(splits) <= {"ind", "ood"} or len(set(splits)) != len(splits):
        raise SystemExit(f"--splits {args.splits!r}: expected ind and/or ood, each once")
    if args.tag is not None and (not args.tag or "_" in args.tag):
        raise SystemExit(f"--tag {args.tag!r}: must be non-empty and hold no '_' (the file names split on it)")
    if not args.follow >= 0:
        raise SystemExit(f"--follow {args.follow}: expected seconds >= 0")

    from pipeline.errors import PipelineError
    from pipeline.plan import Project, parse_set
    from pipeline.sweep import expand, parse_axes

    try:
        project = Project(ROOT / "pipeline.yaml", store=args.store)
        sets = parse_set(args.sets)
        project.check_overrides(sets, "--set")
        points, _ = expand(project, args.sweep, project.profile_name(args.profile), sets, None, parse_axes(args.axes))
    except PipelineError as e:
        raise SystemExit(f"error: {e}") from None
    args.folder.mkdir(parents=True, exist_ok=True)

    def plan(verbose: bool):
        today = dt.date.today().isoformat()
        pols, waiting, collect_key = policies(project, args.sweep, points)
        tag = args.tag or store_tag(project.store, collect_key)
        todo = []
        for split in splits:
            for pol in pols:
                out, done = target(args.folder, file_prefix(pol.stem, pol.seed, split, tag), today)
                if verbose:
                    print(f"{'done   ' if done else 'to run '} {out.name}")
                if not done:
                    todo.append((pol, split, out))
        if verbose:
            for label in waiting:
                print(f"waiting {label}: its rl artifact is not in the store yet")
        return todo, waiting, pols, tag

    if args.dry_run:
        todo, _, pols, tag = plan(True)
        for i, (pol, split, out) in enumerate(todo, 1):
            print(f"[{i}/{len(todo)}] {' '.join(command(pol, split, out, args)[1:])}")
    else:
        def run(pol, split, out):
            cmd = command(pol, split, out, args)
            print("  " + " ".join(cmd[1:]), flush=True)
            subprocess.run(cmd, check=True)

        pols, tag = drain(plan, run, args.follow)
    entries = manifest_entries(args.folder, pols, splits, tag)
    if entries:
        print("comparisons.json entries the finished files support:")
        for e in entries:
            print("  " + json.dumps(e))


if __name__ == "__main__":
    main()
