"""Decide what runs, run it wave by wave on an executor, record the run."""
from __future__ import annotations

import secrets
import shlex
import sys
import time
from dataclasses import dataclass, field
from typing import Sequence

from pipeline.errors import PipelineError
from pipeline.execute import StageFailed
from pipeline.executors import get_executor
from pipeline.plan import Node, Project


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


@dataclass
class RunResult:
    record: dict
    failed: list[StageFailed] = field(default_factory=list)

    @property
    def executed(self) -> list[str]:
        return [n["stage"] for n in self.record["nodes"] if n["action"] == "ran"]

    @property
    def ok(self) -> bool:
        return not self.failed


def unique_nodes(nodes: Sequence[Node]) -> list[Node]:
    """Nodes deduplicated by key (sweep points share ancestors), first occurrence kept."""
    seen: dict[str, Node] = {}
    for n in nodes:
        seen.setdefault(n.key, n)
    return list(seen.values())


def execute(
    project: Project,
    nodes: Sequence[Node],
    runnable: set[str],
    *,
    profile: str | None,
    executor: str = "local",
    jobs: int | None = None,
    device: str | None = None,
    argv: Sequence[str] = (),
    extra_labels: dict[str, list[str]] | None = None,
) -> RunResult:
    """Run every node in ``nodes`` whose status is ``run``; ``runnable`` names the stages allowed to run.

    A node to run whose stage is not runnable (an ancestor excluded by --only/--from) is an error
    raised before anything runs. ``extra_labels`` maps a key to more ref labels to update (sweeps).
    """
    jobs = jobs or project.spec.jobs
    device = device or project.spec.device
    nodes = unique_nodes(nodes)
    for n in nodes:
        if n.status == "run" and n.stage not in runnable:
            raise PipelineError(
                f"stage {n.stage!r} is needed but not cached ({'; '.join(n.reasons)}), and this run may not "
                f"execute it (--only/--from select: {', '.join(sorted(runnable)) or 'nothing'}); run it first"
            )
    run_id = secrets.token_hex(4)
    record = {
        "run_id": run_id,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "argv": list(argv),
        "profile": profile,
        "executor": executor,
        "jobs": jobs,
        "device": device,
        "nodes": [],
        "status": "running",
    }
    by_key = {n.key: n for n in nodes}
    done: set[str] = {n.key for n in nodes if n.status == "cached"}
    failed_keys: set[str] = set()
    failures: list[StageFailed] = []
    total = len(nodes)
    counter = [0]

    def log_node(n: Node, action: str, duration: float = 0.0, note: str = "", error: str = "") -> None:
        counter[0] += 1
        entry = {"stage": n.stage, "key": n.key, "label": n.label, "action": action,
                 "reasons": n.reasons, "duration_s": duration}
        if note:
            entry["note"] = note
        if error:
            entry["error"] = error
        record["nodes"].append(entry)
        why = f" ({'; '.join(n.reasons)})" if action == "ran" and n.reasons else ""
        extra = f" in {duration:.1f} s" if action == "ran" else ""
        say(f"[{counter[0]}/{total}] {n.stage:<10} {n.short}  {action}{extra}{why}{(' - ' + note) if note else ''}")

    for n in nodes:
        if n.status == "cached":
            log_node(n, "cached")

    ex = get_executor(executor, jobs) if any(n.status == "run" for n in nodes) else None
    completed = False
    try:
        while True:
            pending = [n for n in nodes if n.key not in done and n.key not in failed_keys]
            blocked = []
            for n in pending:  # in topological order, so one pass reaches every descendant of a failure
                if any(k in failed_keys for k in n.inputs.values()):
                    failed_keys.add(n.key)
                    blocked.append(n)
                    log_node(n, "skipped", note="an input failed")
            pending = [n for n in pending if n not in blocked]
            wave = [n for n in pending if all(k in done for k in n.inputs.values())]
            if not wave:
                break
            payloads = []
            for n in wave:
                say(f"    {n.stage:<10} {n.short}  running: {'; '.join(n.reasons)}")
                payloads.append(_payload(project, n, by_key, run_id, profile, executor, jobs, device, argv))

            def on_done(p, result, err):
                n = by_key[p["key"]]
                if err is None:
                    done.add(n.key)
                    log_node(n, result["action"], result["duration_s"], result.get("note", ""))
                    for label in (extra_labels or {}).get(n.key, []):
                        project.store.write_ref(label, n.stage, n.key, n.key_inputs)
                else:
                    failed_keys.add(n.key)
                    if not isinstance(err, StageFailed):
                        err = StageFailed(n.stage, n.key, f"{err.__class__.__name__}: {err}", None)
                    failures.append(err)
                    log_node(n, "failed", error=err.error)

            ex.run_wave(payloads, on_done)
        completed = True
    finally:
        if ex is not None:
            ex.close()
        record["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
        record["status"] = ("failed" if failures or failed_keys else "ok") if completed else "interrupted"
        project.store.write_run(record)
    return RunResult(record, failures)


_KEY_OPTIONS = ("-f", "--file", "--store", "--profile", "--set")  # the options that decide which keys a run uses


def rerun_options(argv: Sequence[str], label: str) -> str:
    """The options of ``argv`` a repair command must repeat to hit the same keys, shell-quoted.

    A sweep point's axis values are not in ``argv``; the label is appended so the user can add them.
    """
    out, args = [], list(argv)
    for i, a in enumerate(args):
        name, eq, value = a.partition("=")
        if name in _KEY_OPTIONS:
            out += [name, value] if eq else args[i:i + 2]
    text = shlex.join(out)
    if label.startswith("sweep:"):
        text += f" (plus this sweep point's values as --set: {label.split(':', 2)[2]})"
    return text.strip()


def _payload(project: Project, n: Node, by_key: dict[str, Node], run_id: str, profile, executor, jobs, device,
             argv: Sequence[str] = ()) -> dict:
    inputs = {}
    for stage, key in n.inputs.items():
        inputs[stage] = str(project.store.path(stage, key))
    return {
        "roots": [str(r) for r in project.roots],
        "store_root": str(project.store.root),
        "stage": n.stage,
        "module": n.module,
        "config": n.config,
        "key": n.key,
        "key_inputs": n.key_inputs,
        "inputs": inputs,
        "seed": n.seed,
        "device": device,
        "jobs": jobs,
        "profile": profile or "default",
        "label": n.label,
        "force": "forced" in n.reasons,
        "run_id": run_id,
        "executor": executor,
        "rerun": rerun_options(argv, n.label),
    }
