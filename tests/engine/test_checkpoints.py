"""Checkpoints a stage keeps across a failed or killed run of the same key (pipeline.checkpoints)."""
from __future__ import annotations

import json
import logging
import os
import signal

import pytest

from pipeline.checkpoints import Checkpoints


def test_save_then_load_round_trips_and_replaces(tmp_path):
    cp = Checkpoints(tmp_path / "p")
    assert cp.load("a") is None and cp.names() == []
    with cp.save("a") as d:
        (d / "x.bin").write_bytes(b"one")
        (d / "sub").mkdir()
        (d / "sub" / "y.txt").write_text("two")
    got = cp.load("a")
    assert got is not None and (got / "x.bin").read_bytes() == b"one" and (got / "sub" / "y.txt").read_text() == "two"
    with cp.save("a") as d:
        (d / "x.bin").write_bytes(b"newer")
    assert (cp.load("a") / "x.bin").read_bytes() == b"newer" and not (cp.load("a") / "sub").exists()
    assert cp.names() == ["a"] and not [p for p in (tmp_path / "p").iterdir() if p.name.startswith(".")]


def test_an_exception_inside_save_publishes_nothing(tmp_path):
    cp = Checkpoints(tmp_path / "p")
    with pytest.raises(RuntimeError):
        with cp.save("a") as d:
            (d / "x.bin").write_bytes(b"half")
            raise RuntimeError("killed mid-save")
    assert cp.load("a") is None and list((tmp_path / "p").iterdir()) == []


def test_a_damaged_checkpoint_is_named_removed_and_treated_as_absent(tmp_path, caplog):
    cp = Checkpoints(tmp_path / "p", logging.getLogger("t"))
    with cp.save("a") as d:
        (d / "x.bin").write_bytes(b"abc")
    (tmp_path / "p" / "a" / "x.bin").write_bytes(b"abd")  # same size, other bytes
    with caplog.at_level(logging.WARNING):
        assert cp.load("a") is None
    assert "x.bin differs from its blake3 digest" in caplog.text and cp.names() == []


def test_without_a_store_checkpoints_are_off(tmp_path):
    cp = Checkpoints(None)
    with cp.save("a") as d:
        (d / "x.bin").write_bytes(b"abc")
        written = d
    assert cp.load("a") is None and cp.names() == [] and not written.exists()


@pytest.mark.parametrize("name", ["", ".hidden", "-x", "a/b", "../up"])
def test_bad_names_are_refused(tmp_path, name):
    with pytest.raises(ValueError, match="checkpoint name"):
        Checkpoints(tmp_path).load(name)


def _log(ws) -> list[str]:
    p = ws.root / "cp.log"
    return p.read_text().splitlines() if p.exists() else []


def test_a_failed_stage_keeps_its_checkpoint_and_the_rerun_resumes_with_the_same_result(ws, tmp_path):
    env = {"TEST_CHECKPOINT": "train_wm", "TEST_CHECKPOINT_LOG": ws.root / "cp.log"}
    failed = ws.cli("run", "--until", "train_wm", check=False, TEST_CHECKPOINT_FAIL="train_wm", **env)
    assert failed.returncode == 1 and "checkpoints kept for the next run: half" in failed.stdout + failed.stderr
    assert "resumes from checkpoints: half" in ws.cli("status").stdout
    ws.cli("run", "--until", "train_wm", **env)
    assert _log(ws) == ["train_wm computed", "train_wm resumed"]
    resumed = json.loads(next(ws.store.glob("train_wm/*/*/result.json")).read_text())
    assert not (ws.store / "partial" / "train_wm").exists() or not any((ws.store / "partial" / "train_wm").iterdir())
    # the same key run uninterrupted in a fresh workspace gives the same artifact
    from tests.engine.conftest import make_workspace

    clean = make_workspace(tmp_path / "clean")
    clean.cli("run", "--until", "train_wm", TEST_CHECKPOINT="train_wm")
    assert json.loads(next(clean.store.glob("train_wm/*/*/result.json")).read_text()) == resumed


def test_a_killed_stage_resumes_and_force_starts_over(ws):
    env = {"TEST_CHECKPOINT": "goals", "TEST_CHECKPOINT_LOG": ws.root / "cp.log"}
    ws.cli("run", "--until", "train_wm")
    marker = ws.root / "marker"
    proc = ws.popen_until(marker, "run", "--until", "goals", TEST_SLEEP_STAGE="goals", TEST_SLEEP="60", **env)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert "resumes from checkpoints: half" in ws.cli("status", "--until", "goals").stdout
    assert "drops checkpoints: half" in ws.cli("run", "--until", "goals", "--force", "goals", "--dry-run").stdout
    ws.cli("run", "--until", "goals", **env)
    ws.cli("run", "--until", "goals", "--force", "goals", **env)
    assert _log(ws) == ["goals computed", "goals resumed", "goals computed"]


def test_gc_removes_checkpoints_of_committed_keys_and_keeps_unfinished_ones(ws):
    env = {"TEST_CHECKPOINT": "*"}
    assert ws.cli("run", "--until", "tokenize", check=False, TEST_CHECKPOINT_FAIL="tokenize", **env).returncode == 1
    # a run killed between its commit and dropping its checkpoints leaves them beside a committed key
    stray = ws.store / "partial" / "collect" / next(p.name for p in ws.store.glob("collect/*/*"))
    (stray / "half").mkdir(parents=True)
    (stray / "half" / ".checkpoint.json").write_text('{"files": {}}')
    out = ws.cli("gc").stdout
    assert str(stray) in out and not stray.exists()
    assert "kept the checkpoints of 1 unfinished run(s) (tokenize" in out
    assert "removes" in out and any((ws.store / "partial" / "tokenize").iterdir())
    ws.cli("gc", "--partial")
    assert not any((ws.store / "partial" / "tokenize").iterdir())


def test_a_long_list_of_checkpoints_is_summarised_for_status_lines():
    from pipeline.checkpoints import summarize

    assert summarize(["play"]) == "play"
    assert summarize([f"shard-{i:04d}" for i in range(4)]) == "shard-0000, shard-0001, shard-0002, shard-0003"
    names = [f"shard-{i:04d}" for i in range(100)]
    assert summarize(names) == "shard-0000, shard-0001, shard-0002, shard-0003 and 96 more (100 in all)"
