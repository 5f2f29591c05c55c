"""The content-addressed artifact store.

Layout under the store root::

    <stage>/<key[:2]>/<key>/manifest.json + outputs   committed artifacts
    tmp/<stage>-<key[:12]>-<pid>.<start>-<rand>/      staging dirs (same filesystem), swept by gc
    locks/<key>.lock                                  per-key advisory locks
    refs/<label>/<stage>.json                         the key each label (profile, sweep point) last used
    partial/<stage>/<key>/<name>/                     a running or killed stage's checkpoints
                                                      (pipeline.checkpoints), dropped at commit
    runs/<time>-<id>.json                             run records

A key exists only when its ``manifest.json`` exists and validates. Outputs are written into a
staging dir, the manifest is written last (itself via temp file + rename), and the whole dir is
renamed into place. A crash at any point leaves at most a staging dir, never a half artifact.
"""
from __future__ import annotations

import contextlib
import fcntl
import json
import os
import secrets
import shutil
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import blake3

from pipeline.machine import describe

MANIFEST = "manifest.json"
RESERVED = ("tmp", "locks", "refs", "runs", "sweeps", "partial")  # store directories that are not stages
MANIFEST_SCHEMA = 1
_REQUIRED = ("schema", "stage", "key", "key_inputs", "files", "created")


@dataclass(frozen=True)
class Lookup:
    """What the store holds for a key: ``ok`` (path valid), ``missing``, or ``invalid`` (with why)."""

    state: str
    path: Path
    manifest: dict | None = None
    problem: str = ""

    @property
    def nbytes(self) -> int:
        """Total size of the outputs the manifest lists (0 without a manifest)."""
        return sum(f.get("size", 0) for f in (self.manifest or {}).get("files", {}).values())


def file_digest(path: Path) -> str:
    h = blake3.blake3()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_json_atomic(path: Path, obj: Any) -> None:
    """Write JSON to ``path`` via a temp file in the same dir, fsync, rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=2, sort_keys=True)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class Store:
    """A store rooted at a directory on one filesystem."""

    def __init__(self, root: str | Path):
        self.root = Path(root).resolve()
        for d in ("tmp", "locks", "refs", "runs"):
            (self.root / d).mkdir(parents=True, exist_ok=True)

    # ---- paths -------------------------------------------------------------------------------
    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key[:2] / key

    # ---- reading -----------------------------------------------------------------------------
    def lookup(self, stage: str, key: str) -> Lookup:
        """Whether ``key`` is committed and its manifest is valid; never reads output bytes."""
        path = self.path(stage, key)
        mpath = path / MANIFEST
        if not mpath.exists():
            return Lookup("missing", path)
        try:
            manifest = json.loads(mpath.read_text())
        except (OSError, ValueError) as e:
            return Lookup("invalid", path, problem=f"{mpath}: unreadable manifest ({e.__class__.__name__}: {e})")
        problem = self._check_manifest(manifest, stage, key, path)
        if problem:
            return Lookup("invalid", path, manifest, problem=f"{mpath}: {problem}")
        return Lookup("ok", path, manifest)

    @staticmethod
    def _check_manifest(m: Any, stage: str, key: str, path: Path) -> str:
        problem = Store._check_structure(m, stage, key)
        if problem:
            return problem
        for rel, info in m["files"].items():
            f = path / rel
            try:
                size = f.stat().st_size
            except OSError:
                return f"output {rel} listed in the manifest is missing"
            if size != info.get("size"):
                return f"output {rel} has {size} bytes, the manifest says {info.get('size')}"
        return ""

    @staticmethod
    def _check_structure(m: Any, stage: str, key: str) -> str:
        if not isinstance(m, dict):
            return "manifest is not a JSON object"
        missing = [k for k in _REQUIRED if k not in m]
        if missing:
            return f"manifest lacks {', '.join(missing)}"
        if m["key"] != key or m["stage"] != stage:
            return f"manifest is for {m['stage']}/{m['key']}, not {stage}/{key}"
        if not isinstance(m["files"], dict):
            return "manifest 'files' is not a mapping"
        return ""

    def verify(self, stage: str, key: str) -> list[str]:
        """Re-hash every file of an artifact against its manifest: one line per problem, [] if intact.

        Names each file whose bytes changed (even at the same size), each listed file that is gone
        and each file the manifest does not list. Reads every byte, so planning never calls it;
        `verify`, `show --verify` and a stage about to read its inputs do.
        """
        path = self.path(stage, key)
        mpath = path / MANIFEST
        if not mpath.exists():
            return [f"{path}: no committed artifact ({MANIFEST} is missing)"]
        try:
            m = json.loads(mpath.read_text())
        except (OSError, ValueError) as e:
            return [f"{mpath}: unreadable manifest ({e.__class__.__name__}: {e})"]
        problem = self._check_structure(m, stage, key)
        if problem:
            return [f"{mpath}: {problem}"]
        problems = []
        for rel, info in sorted(m["files"].items()):
            f = path / rel
            if not f.is_file():
                problems.append(f"{f}: listed in the manifest but missing")
            elif f.stat().st_size != info.get("size"):
                problems.append(f"{f}: {f.stat().st_size} bytes, the manifest says {info.get('size')}")
            elif file_digest(f) != info.get("blake3"):
                problems.append(f"{f}: content differs from its blake3 digest in the manifest (same size)")
        for f in sorted(path.rglob("*")):
            if f.is_file() and f != mpath and str(f.relative_to(path)) not in m["files"]:
                problems.append(f"{f}: not listed in the manifest (an extra file)")
        return problems

    # ---- writing -----------------------------------------------------------------------------
    def staging(self, stage: str, key: str) -> Path:
        """A fresh, empty staging dir on the store's filesystem."""
        d = self.root / "tmp" / f"{stage}-{key[:12]}-{_owner()}-{secrets.token_hex(4)}"
        d.mkdir(parents=True)
        return d

    def commit(self, staging: Path, stage: str, key: str, key_inputs: dict, extra: dict | None = None) -> Path:
        """Hash outputs, write the manifest last, rename the staging dir into place.

        If a valid artifact already sits at the key (a concurrent run won), ours is discarded. An
        invalid one is moved aside first. Returns the committed path.
        """
        files = {}
        for p in sorted(staging.rglob("*")):
            if p.is_file() and p.name != MANIFEST:
                rel = str(p.relative_to(staging))
                files[rel] = {"size": p.stat().st_size, "blake3": file_digest(p)}
        manifest = {
            "schema": MANIFEST_SCHEMA,
            "stage": stage,
            "key": key,
            "key_inputs": key_inputs,
            "files": files,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "host": socket.gethostname(),
            "machine": describe(),  # the same key on another CPU kind may hold other bytes (pipeline.machine)
            **(extra or {}),
        }
        write_json_atomic(staging / MANIFEST, manifest)
        fsync_dir(staging)
        final = self.path(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        look = self.lookup(stage, key)
        if look.state == "ok":
            shutil.rmtree(staging, ignore_errors=True)
            return final
        if final.exists():
            self.discard(final)
        os.rename(staging, final)
        fsync_dir(final.parent)
        return final

    def replace(self, stage: str, key: str) -> None:
        """Move a committed artifact aside (for --force): readers then see it as missing."""
        final = self.path(stage, key)
        if final.exists():
            self.discard(final)

    def discard(self, path: Path) -> None:
        """Rename ``path`` into tmp/ (atomic), then delete it."""
        trash = self.root / "tmp" / f"trash-{path.name[:12]}-{_owner()}-{secrets.token_hex(4)}"
        os.rename(path, trash)
        shutil.rmtree(trash, ignore_errors=True)

    # ---- partial work (a stage's checkpoints; pipeline.checkpoints) ----------------------------
    def partial(self, stage: str, key: str) -> Path:
        """The directory of (stage, key)'s checkpoints (it may not exist)."""
        return self.root / "partial" / stage / key

    def open_partial(self, stage: str, key: str) -> Path:
        """``partial(stage, key)`` for the run about to write it; call under the key's lock. Half-written
        checkpoints a killed writer left (``.tmp-*``, ``.trash-*``) are removed: the lock means no
        other writer of this key is alive."""
        d = self.partial(stage, key)
        if d.is_dir():
            for leftover in list(d.glob(".tmp-*")) + list(d.glob(".trash-*")):
                shutil.rmtree(leftover, ignore_errors=True)
        return d

    def drop_partial(self, stage: str, key: str) -> None:
        """Remove (stage, key)'s checkpoints (after its commit, or before a forced rerun)."""
        d = self.partial(stage, key)
        if d.exists():
            self.discard(d)

    def partials(self) -> Iterator[tuple[str, str, Path]]:
        """(stage, key, path) of every checkpoint directory in the store."""
        base = self.root / "partial"
        if not base.is_dir():
            return
        for stage_dir in sorted(p for p in base.iterdir() if p.is_dir()):
            for d in sorted(p for p in stage_dir.iterdir() if p.is_dir()):
                yield stage_dir.name, d.name, d

    # ---- locks -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def lock(self, key: str) -> Iterator[None]:
        """Per-key exclusive advisory lock; blocks until free. Released on exit or process death."""
        fd = os.open(self.root / "locks" / f"{key}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    # ---- refs (what each label last ran, for `status` reasons) --------------------------------
    def _ref_path(self, label: str, stage: str) -> Path:
        safe = label.replace("/", "__")
        return self.root / "refs" / safe / f"{stage}.json"

    def read_ref(self, label: str, stage: str) -> dict | None:
        p = self._ref_path(label, stage)
        try:
            return json.loads(p.read_text())
        except (OSError, ValueError):
            return None

    def write_ref(self, label: str, stage: str, key: str, key_inputs: dict) -> None:
        p = self._ref_path(label, stage)
        p.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(p, {"key": key, "key_inputs": key_inputs})

    # ---- run records -------------------------------------------------------------------------
    def write_run(self, record: dict) -> Path:
        p = self.root / "runs" / f"{record['started'].replace(':', '')}-{record['run_id']}.json"
        write_json_atomic(p, record)
        return p

    def runs(self) -> list[Path]:
        """Run records, oldest first."""
        return sorted(self.root.glob("runs/*.json"))

    # ---- gc ------------------------------------------------------------------------------------
    def committed(self) -> Iterator[tuple[str, str, Path]]:
        """(stage, key, path) of every directory that looks like an artifact slot."""
        for stage_dir in sorted(self.root.iterdir()):
            if stage_dir.name in RESERVED or not stage_dir.is_dir():
                continue
            for prefix in sorted(stage_dir.iterdir()):
                if prefix.is_dir():
                    for art in sorted(prefix.iterdir()):
                        yield stage_dir.name, art.name, art

    def stale_staging(self) -> list[Path]:
        """Staging dirs whose writer process is gone: its pid not alive on this host, a zombie (killed,
        never reaped: an init that reaps no orphans, as in some containers and VMs), or alive with
        another start time (the pid was reused by a later process; pids wrap at pid_max)."""
        out = []
        for d in sorted((self.root / "tmp").iterdir()):
            parts = d.name.rsplit("-", 2)
            pid, _, started = parts[-2].partition(".") if len(parts) == 3 else ("", "", "")
            if not pid.isdigit() or not _pid_alive(int(pid)):
                out.append(d)
                continue
            proc = _proc_stat(int(pid))
            if proc is not None and (proc[0] in ("Z", "X") or (started and proc[1] != started)):
                out.append(d)
        return out


def _proc_stat(pid: int) -> tuple[str, str] | None:
    """Process ``pid``'s state (R, S, Z, ...) and start time (clock ticks since boot), from
    /proc/<pid>/stat fields 3 and 22; None without /proc."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()  # the fields after the command name, from field 3 on
    return fields[0], fields[19]


def _owner() -> str:
    """This process in a staging dir's name: ``<pid>.<start time>`` (``<pid>`` where /proc is absent)."""
    proc = _proc_stat(os.getpid())
    return f"{os.getpid()}.{proc[1]}" if proc else str(os.getpid())


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
