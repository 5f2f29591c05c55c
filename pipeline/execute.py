"""Run one node: lock its key, recheck the store, verify its inputs, run the stage into a staging dir, commit.

``execute_node`` is module-level and takes only plain data, so the local process pool and Ray
tasks call the very same function.
"""
from __future__ import annotations

import importlib
import json
import logging
import random
import shutil
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Mapping

from pipeline.checkpoints import summarize
from pipeline.context import StageContext
from pipeline.errors import PipelineError
from pipeline.progress import Progress
from pipeline.store import Store


class StageFailed(Exception):
    """A stage's run(ctx) raised; carries the stage, key, and where its log was kept."""

    def __init__(self, stage: str, key: str, error: str, log_path: Path | None):
        self.stage, self.key, self.error, self.log_path = stage, key, error, log_path
        super().__init__(f"stage {stage!r} ({key[:12]}) failed: {error}" + (f"\n  log: {log_path}" if log_path else ""))

    def __reduce__(self):  # crosses process-pool and Ray boundaries with all four fields
        return StageFailed, (self.stage, self.key, self.error, self.log_path)


def verify_inputs(store: Store, inputs: Mapping[str, str], rerun: str = "") -> int:
    """Re-hash the input artifacts (stage -> key) a stage is about to read; returns their total bytes.

    Raises PipelineError naming every file that differs from its manifest and the command that
    rebuilds its artifact (``rerun``: the options that select the same keys, e.g. ``--profile toy``).
    """
    total, bad = 0, {}
    for stage, key in sorted(inputs.items()):
        problems = store.verify(stage, key)
        if problems:
            bad[stage] = problems
        else:
            total += store.lookup(stage, key).nbytes
    if bad:
        lines = [f"  {p}" for problems in bad.values() for p in problems]
        force = " ".join(f"--force {s}" for s in bad)
        raise PipelineError(
            "an input artifact does not match its manifest, so the stage did not start:\n" + "\n".join(lines)
            + f"\n  repair: python -m pipeline run {force}{(' ' + rerun) if rerun else ''}"
        )
    return total


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    try:
        import numpy as np

        np.random.seed(seed % 2**32)
    except ImportError:
        pass
    torch = sys.modules.get("torch")  # seeded when the stage uses it; importing it here costs seconds
    if torch is not None:
        torch.manual_seed(seed)


def _stage_logger(stage: str, key: str, log_file: Path) -> tuple[logging.Logger, logging.Handler]:
    """The stage's logger: every record to ``log_file``, those without ``extra={"file_only": True}`` to stderr."""
    log = logging.getLogger(f"stage.{stage}.{key[:12]}")
    log.setLevel(logging.INFO)
    log.propagate = False
    fh = logging.FileHandler(log_file)
    fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(fh)
    if not any(isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler) for h in log.handlers):
        sh = logging.StreamHandler(sys.stderr)
        sh.setFormatter(logging.Formatter(f"  [{stage}] %(message)s"))
        sh.addFilter(lambda record: not getattr(record, "file_only", False))
        log.addHandler(sh)
    return log, fh


def _refuse_changed_code(p: dict[str, Any]) -> None:
    """Fail if the stage's source changed after the run planned its key: the artifact would be filed
    under a key that names code it was not made by (an edit during a long run)."""
    from pipeline.keys import code_digest

    planned = p["key_inputs"].get("code")
    if planned is not None and code_digest(p["module"], p["roots"]) != planned:
        raise StageFailed(p["stage"], p["key"], f"the source of {p['module']} (or a module it imports) changed after "
                          "this run planned its key; nothing was run: run again to plan with the current code", None)


def execute_node(p: dict[str, Any]) -> dict[str, Any]:
    """Run the node described by payload ``p`` unless its key is (by now) committed.

    Returns ``{stage, key, action: ran|cached, duration_s}``; raises StageFailed.
    """
    for r in p["roots"]:
        if r not in sys.path:
            sys.path.insert(0, r)
    store = Store(p["store_root"])
    stage, key = p["stage"], p["key"]
    t0 = time.perf_counter()
    with store.lock(key):
        look = store.lookup(stage, key)
        if look.state == "ok" and not p["force"]:
            store.write_ref(p["label"], stage, key, p["key_inputs"])
            return {"stage": stage, "key": key, "action": "cached", "duration_s": 0.0,
                    "note": "committed by another run while this one waited"}
        t_in = time.perf_counter()
        try:
            in_bytes = verify_inputs(store, p["key_inputs"]["inputs"], p.get("rerun", ""))
        except PipelineError as e:
            raise StageFailed(stage, key, str(e), None) from None
        t_in = time.perf_counter() - t_in
        _refuse_changed_code(p)
        mod = importlib.import_module(p["module"])
        config = mod.Config.model_validate(p["config"])
        staging = store.staging(stage, key)
        if p["force"]:
            store.drop_partial(stage, key)  # --force means from scratch
        partial = store.open_partial(stage, key)
        log, handler = _stage_logger(stage, key, staging / "log.txt")
        from pipeline.executors import mapper_for

        ctx = StageContext(
            stage=stage,
            config=config,
            inputs={n: Path(v) for n, v in p["inputs"].items()},
            out=staging,
            seed=p["seed"],
            device=p["device"],
            jobs=p["jobs"],
            profile=p["profile"],
            log=log,
            mapper=mapper_for(p["executor"]),
            progress_factory=lambda total, desc, unit: Progress(total=total, desc=f"{stage}: {desc}", unit=unit),
            partial=partial,
        )
        _seed_everything(p["seed"])
        try:
            file_only = {"file_only": True}  # the console already has the runner's one-line header
            log.info("started %s %s (profile %s, device %s)", stage, key, p["profile"], p["device"], extra=file_only)
            log.info("config: %s", json.dumps(p["config"], sort_keys=True), extra=file_only)
            resumed = ctx.checkpoints().names()
            if resumed:
                log.info("checkpoints from an earlier, unfinished run of this key: %s", summarize(resumed))
            if p["inputs"]:
                log.info("inputs verified: %s, %.1f MiB in %.2f s", ", ".join(sorted(p["inputs"])), in_bytes / 2**20, t_in)
            mod.run(ctx)
            log.info("finished in %.1f s", time.perf_counter() - t0)
        except BaseException as e:
            log.error("failed: %s\n%s", e, traceback.format_exc())
            handler.close()
            log.removeHandler(handler)
            kept = store.root / "runs" / f"{p['run_id']}-{stage}-{key[:12]}.log"
            try:
                shutil.copyfile(staging / "log.txt", kept)
            except OSError:
                kept = None
            shutil.rmtree(staging, ignore_errors=True)
            if isinstance(e, (KeyboardInterrupt, SystemExit)):
                raise
            resumable = ctx.checkpoints().names()
            if not resumable:
                store.drop_partial(stage, key)
            note = f" (checkpoints kept for the next run: {summarize(resumable)})" if resumable else ""
            raise StageFailed(stage, key, f"{e.__class__.__name__}: {e}{note}", kept) from e
        handler.close()
        log.removeHandler(handler)
        duration = time.perf_counter() - t0
        if p["force"]:
            store.replace(stage, key)
        store.commit(staging, stage, key, p["key_inputs"], extra={
            "duration_s": round(duration, 3), "run_id": p["run_id"], "profile": p["profile"],
            "label": p["label"], "device": p["device"], "module": p["module"],
        })
        store.drop_partial(stage, key)
        store.write_ref(p["label"], stage, key, p["key_inputs"])
    return {"stage": stage, "key": key, "action": "ran", "duration_s": round(duration, 3)}
