"""Pools of several workers set OMP_WAIT_POLICY=PASSIVE in them (pipeline.executors.local.SHARED_CORES_ENV):
torch's threads in processes that share the cores then sleep instead of spinning (benchmarks/wave_threads.py)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from pipeline.executors.local import _pool

ROOT = Path(__file__).resolve().parents[2]


def _wait_policy(workers: int) -> list[str | None]:
    with _pool(workers, fresh=True) as pool:
        return [f.result() for f in [pool.submit(os.getenv, "OMP_WAIT_POLICY") for _ in range(workers)]]


def test_several_workers_sleep_one_worker_keeps_the_default(monkeypatch):
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert _wait_policy(2) == ["PASSIVE", "PASSIVE"]
    assert _wait_policy(1) == [None]
    assert "OMP_WAIT_POLICY" not in os.environ  # the parent's own environment is left alone


def test_the_users_setting_wins(monkeypatch):
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert _wait_policy(2) == ["ACTIVE", "ACTIVE"]


def test_nothing_the_worker_imports_before_its_initializer_loads_torch():
    """OpenMP reads the variable when torch's library loads, so the engine modules a spawned worker
    imports before the initializer runs must not import torch."""
    code = ("import sys, pipeline.__main__, pipeline.executors.local, pipeline.execute; "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False"
