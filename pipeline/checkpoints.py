"""Named checkpoints a stage keeps across a crash or kill of the same key, so the next run resumes.

A long stage (train_wm's three models, wm_play's play then fine-tune) loses everything it finished
when it is killed: its staging dir is discarded. ``ctx.checkpoints()`` gives it a place that
survives: ``<store>/partial/<stage>/<key>/<name>/``. Because the key already names the stage's code,
config and inputs, a checkpoint found there was made by the very same computation, so resuming from
it is safe; the engine drops the directory once the artifact commits (and on ``--force``, which
means "from scratch").

    cp = ctx.checkpoints()
    done = cp.load("action_wm")           # a verified checkpoint directory, or None
    if done is None:
        ...train...
        with cp.save("action_wm") as d:   # a fresh directory; published when the block exits cleanly
            torch.save(state, d / "model.pt")

``save`` writes into a hidden temp dir, records each file's size and blake3 digest, and renames the
directory into place (atomic); a kill mid-save leaves no checkpoint of that name. ``load`` re-hashes
the files and treats a checkpoint whose files differ from their digests as absent (it is removed and
the work is redone), with a warning naming the file. Checkpoints are not artifacts: nothing
downstream reads them, and they never enter a key. A stage that resumes must give the same result
as one that did not (save what the remaining work depends on, RNG state included), which the stage's
tests check. Without a store (a context built by hand in a test) checkpoints are off: ``load``
returns None and ``save``'s directory is thrown away.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import secrets
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from pipeline.store import fsync_dir, file_digest

INDEX = ".checkpoint.json"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def _check_name(name: str) -> None:
    if not _NAME.match(name):
        raise ValueError(f"checkpoint name {name!r}: use letters, digits, '_', '.', '-' (not starting with '.' or '-')")


def summarize(names: list[str], shown: int = 4) -> str:
    """``names`` joined for a status line: all of them up to ``shown``, else the first ``shown`` and a count
    (collect keeps one checkpoint per shard: a hundred names would fill the screen)."""
    if len(names) <= shown:
        return ", ".join(names)
    return f"{', '.join(names[:shown])} and {len(names) - shown} more ({len(names)} in all)"


class Checkpoints:
    """The checkpoints of one (stage, key); ``root`` None: off."""

    def __init__(self, root: Path | None, log: logging.Logger | None = None):
        self.root = root
        self.log = log or logging.getLogger("stage")

    def names(self) -> list[str]:
        """Names of the published checkpoints (not verified)."""
        if self.root is None or not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if p.is_dir() and (p / INDEX).is_file())

    def load(self, name: str) -> Path | None:
        """The directory of checkpoint ``name`` if it exists and every file matches its digest, else None."""
        _check_name(name)
        if self.root is None:
            return None
        d = self.root / name
        if not (d / INDEX).is_file():
            return None
        problem = _verify(d)
        if problem:
            self.log.warning("checkpoint %s is damaged (%s): removed, its work is redone", d, problem)
            self._remove(d)
            return None
        return d

    @contextlib.contextmanager
    def save(self, name: str) -> Iterator[Path]:
        """A fresh directory to write checkpoint ``name`` into; published (replacing an older one) when
        the block exits without an exception, discarded otherwise."""
        _check_name(name)
        if self.root is None:
            with tempfile.TemporaryDirectory(prefix=f"checkpoint-{name}-") as tmp:
                yield Path(tmp)
            return
        self.root.mkdir(parents=True, exist_ok=True)
        tmp = self.root / f".tmp-{name}-{secrets.token_hex(4)}"
        tmp.mkdir()
        try:
            yield tmp
            files = {str(p.relative_to(tmp)): {"size": p.stat().st_size, "blake3": file_digest(p)}
                     for p in sorted(tmp.rglob("*")) if p.is_file()}
            (tmp / INDEX).write_text(json.dumps({"files": files}, indent=1, sort_keys=True) + "\n")
            _fsync_tree(tmp)
            final = self.root / name
            if final.exists():
                self._remove(final)
            os.rename(tmp, final)
            fsync_dir(self.root)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self.log.info("checkpoint %s saved (%d files)", name, len(files))

    def _remove(self, d: Path) -> None:
        trash = d.parent / f".trash-{d.name}-{secrets.token_hex(4)}"
        os.rename(d, trash)
        shutil.rmtree(trash, ignore_errors=True)


def _verify(d: Path) -> str:
    """'' if every file the index lists is there with its size and digest, else what differs."""
    try:
        files = json.loads((d / INDEX).read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        return f"unreadable {INDEX}: {e}"
    for rel, meta in sorted(files.items()):
        p = d / rel
        if not p.is_file():
            return f"{rel} is missing"
        if p.stat().st_size != meta["size"]:
            return f"{rel} has {p.stat().st_size} bytes, its index says {meta['size']}"
        if file_digest(p) != meta["blake3"]:
            return f"{rel} differs from its blake3 digest"
    return ""


def _fsync_tree(d: Path) -> None:
    for p in d.rglob("*"):
        if p.is_file():
            with open(p, "rb+") as f:
                os.fsync(f.fileno())
    fsync_dir(d)
