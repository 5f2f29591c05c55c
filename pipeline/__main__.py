"""CLI: python -m pipeline {run,status,dag,sweep,show,verify,gc}. See README.md."""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

from pipeline.errors import PipelineError
from pipeline.executors import EXECUTORS
from pipeline.plan import Project, parse_set, selection, targets
from pipeline.runner import execute, rerun_options, say


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("-f", "--file", default="pipeline.yaml", help="pipeline spec (default: ./pipeline.yaml)")
    p.add_argument("--store", default=None, help="store directory (default: the spec's `store`, relative to it)")


def _config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--profile", default=None, help="profile overlay (default: the spec's default_profile)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.KEY=VALUE",
                   help="override one config value (YAML value); repeatable")


def _axis_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--axis", dest="axes", action="append", default=[], metavar="STAGE.KEY=[V,...]",
                   help="replace the values of one of the sweep's axes, e.g. rl.seed=[0,1] (YAML list); repeatable")


def _select_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--until", default=None, metavar="S", help="run S and its ancestors only")
    p.add_argument("--only", action="append", default=[], metavar="S", help="run exactly S (repeatable); inputs must be cached")
    p.add_argument("--from", dest="start", default=None, metavar="S", help="run S and its descendants; ancestors must be cached")


def _exec_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dry-run", action="store_true", help="print what would run and why, run nothing")
    p.add_argument("--executor", choices=EXECUTORS, default="local")
    p.add_argument("--jobs", type=int, default=None, help="parallel workers (default: the spec's `jobs`)")
    p.add_argument("--device", default=None, help="torch device for the stages (default: the spec's `device`)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m pipeline", description="content-hashed pipeline runner")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("run", help="run the pipeline (cached stages are skipped)")
    _common(p), _config_args(p), _select_args(p), _exec_args(p)
    p.add_argument("--force", action="append", default=[], metavar="S", help="rerun S even if cached (repeatable)")
    p = sub.add_parser("status", help="each stage: cached or to run, and why")
    _common(p), _config_args(p), _select_args(p)
    p.add_argument("--sweep", default=None, metavar="NAME", help="status of every point of a sweep")
    _axis_arg(p)
    p = sub.add_parser("dag", help="print the stages in order with what they read under a config")
    _common(p), _config_args(p)
    p.add_argument("--dot", action="store_true", help="graphviz dot output")
    p = sub.add_parser("sweep", help="run every point of a sweep and tabulate their metrics")
    _common(p), _config_args(p), _exec_args(p)
    p.add_argument("name")
    p.add_argument("--until", default=None, metavar="S", help="last stage of every point (default: the sweep's `until`)")
    _axis_arg(p)
    p = sub.add_parser("show", help="artifact path and manifest of a stage's current key")
    _common(p), _config_args(p)
    p.add_argument("stage")
    p.add_argument("--verify", action="store_true", help="re-hash every output against the manifest")
    p = sub.add_parser("verify", help="re-hash the current keys' artifacts against their manifests")
    _common(p), _config_args(p)
    p.add_argument("stages", nargs="*", metavar="STAGE", help="stages to verify (default: every stage)")
    p = sub.add_parser("gc", help="remove staging leftovers, old run records, unreferenced artifacts, "
                                  "checkpoints of committed keys")
    _common(p)
    p.add_argument("--dry-run", action="store_true")
    p.add_argument("--keep-runs", type=int, default=20, help="run records to keep (newest)")
    p.add_argument("--partial", action="store_true",
                   help="also remove the checkpoints of unfinished runs (the next run of those keys starts over)")
    return ap


def _status_table(nodes, header: str | None = None) -> None:
    if header:
        print(header)
    for n in nodes:
        state = "cached" if n.status == "cached" else "; ".join(n.reasons)
        print(f"  {n.stage:<10} {n.short}  {state}")


def cmd_dag(project: Project, args) -> int:
    """The stages in order with their declared needs; a need the stage's config (under --profile and
    --set) does not read (its module's ``unread_needs``) is marked: it is neither waited for nor keyed."""
    profile, sets = _prepare(project, args)
    unread = {s: [n for n in project.needs[s] if n not in project.used_needs(s, project.config(s, profile, sets))]
              for s in project.order}
    if args.dot:
        print("digraph pipeline {\n  rankdir=LR;")
        for s in project.order:
            print(f'  "{s}";')
            for need in project.needs[s]:
                style = " [style=dashed, label=\"unread\"]" if need in unread[s] else ""
                print(f'  "{need}" -> "{s}"{style};')
        print("}")
        return 0
    width = max(len(s) for s in project.order)
    for i, s in enumerate(project.order, 1):
        read = [n for n in project.needs[s] if n not in unread[s]]
        line = f"{i}. {s:<{width}}  <- {', '.join(read)}" if read else f"{i}. {s}"
        if unread[s]:
            line += f"  (declared, unread under this config: {', '.join(unread[s])})"
        print(line)
    return 0


def _prepare(project: Project, args):
    profile = project.profile_name(args.profile)
    sets = parse_set(args.sets)
    project.check_overrides(sets, "--set")
    return profile, sets


def cmd_run(project: Project, args, argv) -> int:
    profile, sets = _prepare(project, args)
    stages = selection(project, args.until, args.only, args.start)
    for f in args.force:
        if f not in project.needs:
            raise PipelineError(f"--force: unknown stage {f!r}; known stages: {', '.join(project.order)}")
    nodes = project.plan(targets(project, stages, args.only), profile, sets, label=profile or "default", force=args.force)
    if args.dry_run:
        _status_table(nodes, f"profile {profile}: {sum(n.status == 'run' for n in nodes)} to run")
        return 0
    result = execute(project, nodes, set(stages), profile=profile, executor=args.executor, jobs=args.jobs,
                     device=args.device, argv=argv)
    for f in result.failed:
        say(f"error: {f}")
    return 0 if result.ok else 1


def cmd_status(project: Project, args) -> int:
    profile, sets = _prepare(project, args)
    if args.sweep:
        from pipeline.sweep import expand, parse_axes

        points, _ = expand(project, args.sweep, profile, sets, args.until, parse_axes(args.axes))
        for pt in points:
            _status_table(pt.nodes, pt.label)
        return 0
    stages = selection(project, args.until, args.only, args.start)
    _status_table(project.plan(targets(project, stages, args.only), profile, sets, label=profile or "default"),
                  f"profile: {profile}")
    return 0


def cmd_sweep(project: Project, args, argv) -> int:
    from pipeline.sweep import expand, parse_axes, results_table, run_report

    profile, sets = _prepare(project, args)
    points, last = expand(project, args.name, profile, sets, args.until, parse_axes(args.axes))
    if args.dry_run:
        for pt in points:
            _status_table(pt.nodes, pt.label)
        return 0
    labels: dict[str, list[str]] = {}
    nodes = []
    for pt in points:
        nodes.extend(pt.nodes)
        for n in pt.nodes:
            labels.setdefault(n.key, []).append(pt.label)
    result = execute(project, nodes, set(project.order), profile=profile, executor=args.executor, jobs=args.jobs,
                     device=args.device, argv=argv, extra_labels=labels)
    for f in result.failed:
        say(f"error: {f}")
    if not result.ok:
        return 1
    out = results_table(project, args.name, points)
    print((out / "results.md").read_text())
    report = run_report(project, args.name, points, out)
    if report is not None:
        say(f"sweep {args.name}: report in {report}")
    say(f"sweep {args.name}: {len(points)} points up to {last}; table in {out}/results.{{md,csv,json}}")
    return 0


def cmd_show(project: Project, args) -> int:
    profile, sets = _prepare(project, args)
    if args.stage not in project.needs:
        raise PipelineError(f"show: unknown stage {args.stage!r}; known stages: {', '.join(project.order)}")
    node = [n for n in project.plan([args.stage], profile, sets, label=profile or "default") if n.stage == args.stage][0]
    look = project.store.lookup(node.stage, node.key)
    print(f"{node.stage} {node.key}\npath: {look.path}\nstate: {look.state}{(' - ' + look.problem) if look.problem else ''}")
    if look.manifest is not None:
        print(json.dumps(look.manifest, indent=2, sort_keys=True))
    if look.path is not None and (Path(look.path) / "tensorboard").is_dir():
        print(f"training curves: tensorboard --logdir {Path(look.path) / 'tensorboard'}")
    if args.verify:
        problems = project.store.verify(node.stage, node.key)
        print("verify: ok" if not problems else "verify: FAILED\n  " + "\n  ".join(problems))
        return 0 if not problems else 1
    return 0 if look.state == "ok" else 1


def cmd_verify(project: Project, args, argv) -> int:
    """Re-hash each selected stage's artifact at its current key; 1 and every bad file named if any differ."""
    profile, sets = _prepare(project, args)
    for s in args.stages:
        if s not in project.needs:
            raise PipelineError(f"verify: unknown stage {s!r}; known stages: {', '.join(project.order)}")
    wanted = args.stages or project.order
    nodes = [n for n in project.plan(wanted, profile, sets, label=profile or "default") if n.stage in wanted]
    print(f"profile: {profile}")
    bad = []
    for n in nodes:
        if project.store.lookup(n.stage, n.key).state == "missing":
            print(f"  {n.stage:<10} {n.short}  not built, nothing to verify")
            continue
        t = time.perf_counter()
        problems = project.store.verify(n.stage, n.key)
        if problems:
            bad.append(n.stage)
            print(f"  {n.stage:<10} {n.short}  FAILED\n" + "\n".join(f"      {p}" for p in problems))
        else:
            look = project.store.lookup(n.stage, n.key)
            print(f"  {n.stage:<10} {n.short}  ok ({len(look.manifest['files'])} files, {look.nbytes / 2**20:.1f} MiB "
                  f"in {time.perf_counter() - t:.2f} s)")
    if bad:
        rerun = rerun_options(argv, profile or "default")
        say(f"error: {len(bad)} artifact(s) differ from their manifests ({', '.join(bad)}); repair: python -m pipeline run "
            + " ".join(f"--force {s}" for s in bad) + (f" {rerun}" if rerun else ""))
        return 1
    return 0


def cmd_gc(project: Project, args) -> int:
    store = project.store
    doomed: list[Path] = list(store.stale_staging())
    runs = store.runs()
    old_runs = runs[: max(len(runs) - args.keep_runs, 0)]
    doomed.extend(old_runs)
    keep: set[str] = set()
    for r in runs[len(old_runs):]:
        try:
            keep.update(n["key"] for n in json.loads(r.read_text()).get("nodes", []))
        except (OSError, ValueError):
            continue
    for ref in (store.root / "refs").rglob("*.json"):
        try:
            keep.add(json.loads(ref.read_text())["key"])
        except (OSError, ValueError, KeyError):
            continue
    doomed.extend(path for _, key, path in store.committed() if key not in keep)
    kept_partial = []
    for stage, key, path in store.partials():  # a run killed between its commit and dropping them, or --partial
        if args.partial or store.lookup(stage, key).state == "ok":
            doomed.append(path)
        else:
            kept_partial.append(f"{stage} {key[:12]}")
    for d in doomed:
        print(f"{'would remove' if args.dry_run else 'remove'} {d}")
        if not args.dry_run:
            if d.is_dir():
                store.discard(d) if d.parent.parent.parent == store.root else shutil.rmtree(d, ignore_errors=True)
            else:
                d.unlink(missing_ok=True)
    print(f"gc: {len(doomed)} item(s) {'to remove' if args.dry_run else 'removed'}")
    if kept_partial:
        print(f"gc: kept the checkpoints of {len(kept_partial)} unfinished run(s) ({', '.join(kept_partial)}); "
              "their next run resumes from them; --partial removes them")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    try:
        project = Project(args.file, args.store)
        if args.cmd == "dag":
            return cmd_dag(project, args)
        if args.cmd == "run":
            return cmd_run(project, args, argv)
        if args.cmd == "status":
            return cmd_status(project, args)
        if args.cmd == "sweep":
            return cmd_sweep(project, args, argv)
        if args.cmd == "show":
            return cmd_show(project, args)
        if args.cmd == "verify":
            return cmd_verify(project, args, argv)
        if args.cmd == "gc":
            return cmd_gc(project, args)
    except PipelineError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 2


if __name__ == "__main__":
    sys.exit(main())
