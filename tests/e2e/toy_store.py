"""The toy store the end-to-end files share, and their helpers for the real CLI.

Every stage at the toy profile runs once per test session (``built_toy_store``, under a file lock,
whichever xdist worker gets there first; the others wait for it), and each module gets its own copy
(``store``): the modules then run at once on separate workers, and each writes only into its copy (a
test may read "the newest rl artifact" of its store). Before 2026-12-05 one file held every test and
built its own store, and one worker held it for nearly the whole run: the suite took 1,050 s of tests
on a 2-core EPYC that way and 942 s split (fresh clones, 2026-12-05, docs/RESULTS.md).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
STAGES = ["collect", "tokenize", "train_wm", "goals", "sft", "wm_play", "rl", "evaluate"]


def cli(store: Path, *args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "pipeline", *args, "--store", str(store)], cwd=REPO,
                          capture_output=True, text=True, timeout=3000)
    assert proc.returncode == 0, f"pipeline {' '.join(args)} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr[-6000:]}"
    return proc


def actions(proc: subprocess.CompletedProcess) -> Counter:
    """(stage, action) counts from the runner's '[i/n] stage key action' lines."""
    out = Counter()
    for line in proc.stderr.splitlines():
        parts = line.split()
        if len(parts) >= 4 and parts[0].startswith("[") and parts[0].endswith("]") and "/" in parts[0]:
            out[(parts[1], parts[3])] += 1
    return out


def artifact(store: Path, stage: str) -> Path:
    arts = sorted((store / stage).glob("*/*/manifest.json"), key=lambda p: p.stat().st_mtime)
    assert arts, f"no {stage} artifact in {store}"
    return arts[-1].parent


def shown(store: Path, stage: str, *sets: str) -> Path:
    """The artifact of ``stage`` at the toy profile's key, under ``sets`` if given (``pipeline show``).

    In this process: the CLI's own ``main``, without the ~3 s a fresh interpreter takes to import it
    (this module asks ~20 times; ``test_all_eight_stages...`` runs ``show`` as a subprocess)."""
    import contextlib
    import io

    from pipeline.__main__ import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(["show", stage, "--profile", "toy", *sets, "--store", str(store), "--file", str(REPO / "pipeline.yaml")])
    assert rc == 0, f"pipeline show {stage} {' '.join(sets)} exited {rc}\n{out.getvalue()}"
    return Path(out.getvalue().splitlines()[1].removeprefix("path: "))



def built_toy_store(tmp_path_factory) -> Path:
    """The session's toy store with every stage run once (built here by the first caller)."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "e2e_toy"  # xdist: the session's root
    root.mkdir(parents=True, exist_ok=True)
    with FileLock(str(root / "build.lock")):
        built = root / "built.txt"  # written after the build passed its check
        if not built.is_file():
            first = cli(root / "artifacts", "run", "--profile", "toy")
            assert all(actions(first)[(s, "ran")] == 1 for s in STAGES), first.stderr[-3000:]
            built.write_text(first.stderr)
    return root / "artifacts"


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    """This module's copy of the session's toy store (same keys: every stage reads as cached)."""
    copy = tmp_path_factory.mktemp("toy") / "artifacts"
    shutil.copytree(built_toy_store(tmp_path_factory), copy, symlinks=True)  # mtimes kept: "newest" stays newest
    return copy
