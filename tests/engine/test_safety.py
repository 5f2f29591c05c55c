"""Crash safety, corrupted manifests, concurrent runs, failing stages, gc."""
from __future__ import annotations

import json
import os
import signal
import time
from collections import Counter

ALL = ["collect", "tokenize", "train_wm", "goals", "rl", "evaluate"]


def _manifests(ws) -> dict[str, list]:
    return {s: sorted((ws.store / s).glob("*/*/manifest.json")) for s in ALL}


def test_sigkill_mid_write_leaves_no_manifest_and_next_run_completes(ws):
    ws.cli("run", "--until", "train_wm")
    before = {s: [p.read_bytes() for p in ms] for s, ms in _manifests(ws).items()}
    marker = ws.root / "marker"
    proc = ws.popen_until(marker, "run", TEST_SLEEP_STAGE="goals", TEST_SLEEP="60")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    after = _manifests(ws)
    assert after["goals"] == [] and after["rl"] == [] and after["evaluate"] == []
    assert {s: [p.read_bytes() for p in after[s]] for s in ("collect", "tokenize", "train_wm")} == {
        s: before[s] for s in ("collect", "tokenize", "train_wm")}
    assert list((ws.store / "tmp").glob("goals-*"))  # only staging garbage was left
    ws.reset_log()
    st = ws.cli("status").stdout
    assert "goals" in st and "missing" in st
    ws.cli("run")
    assert ws.executions() == ["goals", "rl", "evaluate"]
    gc = ws.cli("gc").stdout
    assert "goals-" in gc and not list((ws.store / "tmp").glob("goals-*"))
    assert all(_manifests(ws)[s] for s in ALL)  # gc kept every referenced artifact


def test_truncated_or_invalid_manifest_is_reported_and_rerun(ws):
    ws.cli("run")
    m = _manifests(ws)["goals"][0]
    m.write_text(m.read_text()[:40])
    st = ws.cli("status").stdout
    assert "goals" in st and "invalid artifact" in st and "unreadable manifest" in st
    ws.reset_log()
    ws.cli("run")
    assert ws.executions() == ["goals"]  # same key, so descendants stay cached
    m = _manifests(ws)["rl"][0]
    data = json.loads(m.read_text())
    data["files"]["result.json"]["size"] += 1
    m.write_text(json.dumps(data))
    assert "has " in ws.cli("status").stdout
    ws.reset_log()
    ws.cli("run")
    assert ws.executions() == ["rl"]


def test_two_concurrent_runs_execute_each_key_once(ws):
    a = ws.popen("run", TEST_SLEEP_STAGE="*", TEST_SLEEP="0.4")
    b = ws.popen("run", TEST_SLEEP_STAGE="*", TEST_SLEEP="0.4")
    outs = [p.communicate(timeout=120) for p in (a, b)]
    assert a.returncode == 0 and b.returncode == 0, outs
    assert Counter(ws.executions()) == {s: 1 for s in ALL}
    assert all(len(ms) == 1 for ms in _manifests(ws).values())


def test_failing_stage_names_itself_keeps_its_log_and_commits_nothing(ws):
    r = ws.cli("run", "--set", "rl.fail=true", check=False)
    assert r.returncode == 1
    assert "stage 'rl'" in r.stderr and "rl was told to fail" in r.stderr
    assert "evaluate" in r.stderr and "skipped" in r.stderr
    assert _manifests(ws)["rl"] == [] and _manifests(ws)["evaluate"] == []
    logs = list((ws.store / "runs").glob("*-rl-*.log"))
    assert logs and "rl was told to fail" in logs[0].read_text()
    assert not list((ws.store / "tmp").glob("rl-*"))
    rec = json.loads(sorted((ws.store / "runs").glob("*.json"))[-1].read_text())
    assert rec["status"] == "failed"


def _alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie waiting to be reaped counts as dead)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_sigkill_of_a_parallel_sweep_takes_its_workers_down_and_the_rerun_completes(ws):
    ws.cli("run", "--until", "goals")
    marker = ws.root / "marker"
    proc = ws.popen_until(marker, "sweep", "rewards", "--until", "rl", "--jobs", "2", TEST_SLEEP_STAGE="rl", TEST_SLEEP="120")
    workers = [int(line.split()[1]) for line in ws.exec_log.read_text().splitlines() if line.startswith("rl ")]
    assert workers and all(w != proc.pid for w in workers)  # the rl points run in pool workers
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 10
    while any(_alive(w) for w in workers) and time.time() < deadline:
        time.sleep(0.1)
    assert not any(_alive(w) for w in workers), "pool workers outlived the killed sweep"
    ws.reset_log()
    ws.cli("sweep", "rewards", "--until", "rl", "--jobs", "2")  # not blocked by a surviving worker's lock
    assert Counter(ws.executions())["rl"] == 12


def test_a_stage_whose_source_changed_during_the_run_refuses_to_run(ws):
    marker = ws.root / "tokenize.started"
    proc = ws.popen_until(marker, "run", "--until", "train_wm", TEST_SLEEP_STAGE="tokenize", TEST_SLEEP="2")
    src = ws.root / "ts" / "train_wm.py"  # planned already: its key names the source as it was
    src.write_text(src.read_text() + "\n# edited while the run was going\n")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1, err
    assert "changed after this run planned its key" in err
    assert ws.executions() == ["collect", "tokenize"]  # train_wm never started
    ws.reset_log()
    ws.cli("run", "--until", "train_wm")  # planned again with the edited source: runs under a new key
    assert ws.executions() == ["train_wm"]


def test_gc_tells_a_staging_dir_of_a_dead_writer_from_one_whose_pid_was_reused(tmp_path):
    """pids wrap (pid_max), so a live pid alone does not prove the staging dir's writer is alive."""
    from pipeline.store import Store

    store = Store(tmp_path / "store")
    mine = store.staging("goals", "a" * 64)  # this process: alive, same start time
    pid, started = mine.name.rsplit("-", 2)[-2].split(".")
    assert int(pid) == os.getpid() and started.isdigit()
    reused = store.root / "tmp" / f"goals-{'b' * 12}-{pid}.{int(started) + 1}-0000"  # same pid, another process
    reused.mkdir()
    legacy = store.root / "tmp" / f"goals-{'c' * 12}-{pid}-0000"  # a name without the start time: pid only
    legacy.mkdir()
    assert store.stale_staging() == [reused]


def test_gc_takes_a_killed_but_unreaped_writer_for_dead(tmp_path):
    """A writer killed with its run and never reaped (an init that reaps no orphans) stays a zombie:
    its pid answers signal 0 with its own start time, yet it will never commit."""
    import subprocess

    from pipeline.store import Store, _proc_stat

    store = Store(tmp_path / "store")
    store.staging("goals", "a" * 64)  # this process: alive
    child = subprocess.Popen(["true"])  # exits at once; a zombie until waited for
    try:
        deadline = time.time() + 10
        while _proc_stat(child.pid)[0] != "Z":
            assert time.time() < deadline
            time.sleep(0.01)
        zombie = store.root / "tmp" / f"goals-{'b' * 12}-{child.pid}.{_proc_stat(child.pid)[1]}-0000"
        zombie.mkdir()
        assert store.stale_staging() == [zombie]
    finally:
        child.wait()
