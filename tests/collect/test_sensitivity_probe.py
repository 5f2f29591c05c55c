"""scripts/outcome_sensitivity_probe.py through its entry point: a demonstration replays to success
undisturbed, and the table counts the replays with the object moved."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.sim
ROOT = Path(__file__).resolve().parents[2]


def test_a_demonstration_replays_and_the_moved_replays_are_counted(tmp_path):
    out = tmp_path / "rows.json"
    run = subprocess.run([sys.executable, "scripts/outcome_sensitivity_probe.py", "--tasks", "push", "--seeds", "1",
                          "--deltas", "0.5", "8", "--directions", "2", "--out", str(out)],
                         cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    rows = json.loads(out.read_text())
    assert len(rows) == 4 and all(r["task"] == "push" and r["base"] for r in rows)  # the plan replays to success
    near = [r["success"] for r in rows if r["delta_cm"] == 0.5]
    assert near == [True, True]  # half a centimetre does not undo a plan (128 of 128 over the four tasks)
    assert all(isinstance(r["success"], bool) for r in rows)
    assert 0.3 < rows[0]["cm_per_pixel"] < 3.0
    assert "| push | " in run.stdout and "| all | " in run.stdout and "/2 = " in run.stdout
