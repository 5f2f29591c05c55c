"""Shard-level resume of the collect stage.

Each finished shard is saved as a checkpoint of the stage's key (``pipeline.checkpoints``): the shard
file (hard-linked where the filesystem allows, else copied) and the worker's result (episode metas and
counters). A run killed mid-collection (``kill -9``, a lost session) resumes at the next run with the
same key: a shard whose checkpoint verifies is put back in place, unchanged, instead of being collected
again; the shard being written when the run died is redone (its temp file never became a shard). A
shard's episodes depend only on its job (scenes, kinds and seeds are planned up front), so the resumed
artifact holds what an uninterrupted run on the same machine writes.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from pipeline.checkpoints import Checkpoints

RESULT = "result.json"


def checkpoint_name(shard_path: str | Path) -> str:
    """``shard-<task>-<index>``: one checkpoint per shard file."""
    return f"shard-{Path(shard_path).stem}"


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:  # another filesystem, or links not allowed
        shutil.copyfile(src, dst)


def collect_or_resume(job: dict) -> dict:
    """``collect_shard(job)``, or the saved result of an earlier run of this key that finished this shard.

    ``job["checkpoints"]``: the key's checkpoint directory (None: no resume, nothing saved)."""
    from stages.collect.worker import collect_shard

    root = job.get("checkpoints")
    ckpt = Checkpoints(Path(root) if root else None)
    shard = Path(job["path"])
    name = checkpoint_name(shard)
    saved = ckpt.load(name)  # None when absent or damaged (a damaged one is removed and redone)
    if saved is not None:
        _link_or_copy(saved / shard.name, shard)
        return {**json.loads((saved / RESULT).read_text()), "resumed": True}  # not collected by this run
    result = collect_shard({k: v for k, v in job.items() if k != "checkpoints"})
    if root:
        with ckpt.save(name) as d:
            _link_or_copy(shard, d / shard.name)
            (d / RESULT).write_text(json.dumps(result) + "\n")
    return result
