"""Artifact integrity: `verify` names every changed, missing or extra file; a stage refuses corrupt inputs."""
from __future__ import annotations

import sys

import pytest

import pipeline.store
from pipeline.__main__ import main


def _artifact(ws, stage: str):
    (path,) = (ws.store / stage).glob("*/*")
    return path


def _flip_same_size(path) -> None:
    data = bytearray(path.read_bytes())
    data[0] ^= 1
    path.write_bytes(bytes(data))


def test_verify_is_ok_on_fresh_artifacts_and_skips_unbuilt_stages(ws):
    ws.cli("run", "--until", "tokenize")
    out = ws.cli("verify").stdout
    assert "collect" in out and "tokenize" in out and out.count(" ok (") == 2
    assert "rl " in out and "not built" in out


def test_verify_names_a_same_size_byte_flip(ws):
    ws.cli("run", "--until", "tokenize")
    bad = _artifact(ws, "collect") / "result.json"
    _flip_same_size(bad)
    proc = ws.cli("verify", check=False)
    assert proc.returncode == 1
    assert f"{bad}: content differs" in proc.stdout
    assert "python -m pipeline run --force collect" in proc.stderr
    assert ws.cli("verify", "tokenize").returncode == 0  # naming a stage verifies only that stage


def test_verify_names_a_deleted_file_and_an_extra_file(ws):
    ws.cli("run", "--until", "tokenize")
    art = _artifact(ws, "tokenize")
    (art / "metrics.json").unlink()
    (art / "stray.bin").write_bytes(b"not mine")
    proc = ws.cli("verify", "tokenize", check=False)
    assert proc.returncode == 1
    assert f"{art / 'metrics.json'}: listed in the manifest but missing" in proc.stdout
    assert f"{art / 'stray.bin'}: not listed in the manifest" in proc.stdout


def test_a_forced_stage_refuses_a_corrupt_input_and_nothing_downstream_runs(ws):
    ws.cli("run", "--until", "tokenize")
    bad = _artifact(ws, "collect") / "result.json"
    _flip_same_size(bad)
    ws.reset_log()
    proc = ws.cli("run", "--force", "tokenize", "--profile", "toy", check=False)
    assert proc.returncode == 1
    assert ws.executions() == []  # tokenize did not start, so train_wm and the rest did not either
    assert proc.stderr.count("skipped - an input failed") == 4  # train_wm, goals, rl, evaluate: all named
    assert str(bad) in proc.stderr and "content differs" in proc.stderr
    assert "repair: python -m pipeline run --force collect --profile toy" in proc.stderr
    ws.cli("run", "--force", "collect", "--profile", "toy")  # the repair command
    assert ws.executions() == ["collect", "train_wm", "goals", "rl", "evaluate"]  # tokenize's key was intact
    assert ws.cli("verify").returncode == 0


def test_a_failure_in_a_pool_worker_reaches_the_parent_with_its_message(ws):
    """StageFailed (a corrupt input, a failing stage) must survive unpickling in the parent."""
    proc = ws.cli("sweep", "rewards", "--axis", "rl.reward=[wm]", "--axis", "rl.seed=[0, 1]", "--jobs", "2",
                  "--set", "rl.fail=true", check=False)
    assert proc.returncode == 1
    assert proc.stderr.count("failed: RuntimeError: rl was told to fail") == 2  # not BrokenProcessPool
    assert "BrokenProcessPool" not in proc.stderr


def test_cached_run_and_status_read_no_artifact_bytes(ws, monkeypatch, capsys):
    ws.cli("run")

    def no_hashing(path):
        raise AssertionError(f"hashed {path}")

    monkeypatch.setattr(pipeline.store, "file_digest", no_hashing)
    monkeypatch.chdir(ws.root)
    monkeypatch.setenv("TEST_EXEC_LOG", str(ws.exec_log))
    monkeypatch.setattr(sys, "path", list(sys.path))  # in-process CLI: the workspace's `ts` package goes on it
    ws.reset_log()
    try:
        assert main(["run"]) == 0
        assert main(["status"]) == 0
        assert ws.executions() == []
        assert "cached" in capsys.readouterr().out
        with pytest.raises(AssertionError, match="hashed"):  # the patch is live: verify does hash
            main(["verify", "collect"])
    finally:
        for name in [m for m in sys.modules if m == "ts" or m.startswith("ts.")]:
            del sys.modules[name]
