"""A copy of the test stages in a temp dir (so tests may edit their source), and a CLI runner."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


@dataclass
class Workspace:
    root: Path
    exec_log: Path

    def env(self, **extra) -> dict:
        env = {**os.environ, "PYTHONPATH": f"{REPO}", "TEST_EXEC_LOG": str(self.exec_log), "PIPELINE_PROGRESS": "0"}
        env.update({k: str(v) for k, v in extra.items()})
        return env

    def cli(self, *args: str, check: bool = True, **env) -> subprocess.CompletedProcess:
        """Run ``python -m pipeline ARGS`` in the workspace; returns the completed process."""
        proc = subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=self.root, env=self.env(**env),
                              capture_output=True, text=True, timeout=300)
        if check and proc.returncode != 0:
            raise AssertionError(f"pipeline {' '.join(args)} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
        return proc

    def popen(self, *args: str, **env) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "pipeline", *args], cwd=self.root, env=self.env(**env),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def popen_until(self, marker: Path, *args: str, timeout: float = 60, **env) -> subprocess.Popen:
        """``popen(*args, TEST_MARKER=marker, **env)``, returned once the stage has created ``marker``."""
        proc = self.popen(*args, TEST_MARKER=marker, **env)
        deadline = time.time() + timeout
        while not marker.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.time() < deadline, f"no {marker} after {timeout} s"
            time.sleep(0.05)
        return proc

    def executions(self) -> list[str]:
        """Stage names in the order they executed since the last reset."""
        if not self.exec_log.exists():
            return []
        return [line.split()[0] for line in self.exec_log.read_text().splitlines() if line.strip()]

    def reset_log(self) -> None:
        self.exec_log.unlink(missing_ok=True)

    @property
    def spec(self) -> Path:
        return self.root / "pipeline.yaml"

    @property
    def store(self) -> Path:
        return self.root / "artifacts"


def make_workspace(root: Path) -> Workspace:
    """Copy tests/engine/teststages to ``root/ts`` as package ``ts`` with its own pipeline.yaml."""
    pkg = root / "ts"
    shutil.copytree(HERE / "teststages", pkg, ignore=shutil.ignore_patterns("__pycache__", "pipeline.yaml"))
    for f in pkg.glob("*.py"):
        f.write_text(f.read_text().replace("tests.engine.teststages", "ts"))
    spec = (HERE / "teststages" / "pipeline.yaml").read_text().replace("tests.engine.teststages", "ts")
    (root / "pipeline.yaml").write_text(spec)
    return Workspace(root, root / "exec.log")


@pytest.fixture
def ws(tmp_path) -> Workspace:
    return make_workspace(tmp_path)
