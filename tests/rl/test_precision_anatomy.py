"""scripts/precision_anatomy.py: hand-made imagined.json rows give known counts by done step, task and
the replay's fate; a recount at a stricter threshold or hold follows the recorded probabilities; a
malformed file is refused by name."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "scripts" / "precision_anatomy.py"


def _row(env: str, probs: list[float], first_success: int, theta: float = 0.5) -> dict:
    from stages.rl.imagined import replay_row

    row = vars(replay_row(env, np.asarray(probs), first_success, theta))
    return {k: list(v) if isinstance(v, tuple) else v for k, v in row.items()}


def _artifact(folder: Path) -> Path:
    """IND: push fires at step 2 (real, replay succeeds at 2), push at 12 (replay at 14: 2 late), pull at 25
    (never real), pull never fires; OOD: one move_to_aim fires at step 1, real."""
    low = [0.1] * 30
    table = {"ind": [_row("push/a", [0.1, 0.9] + low[2:], 2),
                     _row("push/b", low[:11] + [0.9, 0.2, 0.9, 0.9, 0.9] + low[16:], 14),
                     _row("pull/c", low[:24] + [0.95] + low[25:], -1),
                     _row("pull/d", low, 7)],
             "ood": [_row("move_to_aim/e", [0.8] + low[1:], 1)]}
    folder.mkdir()
    (folder / "imagined.json").write_text(json.dumps(table))
    return folder


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, cwd=REPO)


def test_counts_by_step_task_and_fate(tmp_path):
    rl = _artifact(tmp_path / "rl")
    out = _run(rl, "--json", tmp_path / "a.json")
    assert out.returncode == 0, out.stderr
    rep = json.loads((tmp_path / "a.json").read_text())["splits"]
    ind = rep["ind"]
    assert ind["environments"] == 4 and (ind["all"]["real"], ind["all"]["imagined"]) == (1, 3)
    assert {b: (r["real"], r["imagined"]) for b, r in ind["by_step"].items()} == {"1-10": (1, 1), "11-20": (0, 1), "21-40": (0, 1)}
    assert {t: (r["real"], r["imagined"]) for t, r in ind["by_task"].items()} == {"pull": (0, 1), "push": (1, 2)}
    assert ind["fate"] == {"real": 1, "later by <= 3": 1, "never": 1}
    assert (ind["slack"]["3"]["real"], ind["slack"]["10"]["real"]) == (2, 2)
    assert rep["ood"]["all"]["precision"] == 1.0
    assert "ind: 4 environments, imagined successes real 1/3 = 0.33" in out.stdout


def test_a_stricter_hold_recounts_from_the_recorded_probabilities(tmp_path):
    rl = _artifact(tmp_path / "rl")
    out = _run(rl, rl, "--theta", "0.5", "--persist", "3", "--json", tmp_path / "a.json")  # the same artifact twice: pooled
    assert out.returncode == 0, out.stderr
    ind = json.loads((tmp_path / "a.json").read_text())["splits"]["ind"]
    # held 3 steps: only push/b (0.9 at steps 14-16 -> done at 16, replay succeeded at 14: real)
    assert ind["environments"] == 8 and (ind["all"]["real"], ind["all"]["imagined"]) == (2, 2)
    assert _run(rl, "--persist", "3").returncode != 0  # the stage's threshold is not recorded: refused


def test_a_missing_or_malformed_file_is_named(tmp_path):
    out = _run(tmp_path / "nothing")
    assert out.returncode != 0 and "nothing/imagined.json: no such file" in out.stderr
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "imagined.json").write_text(json.dumps({"ind": [{"env_id": "push/a", "done_at": 1, "success": True, "oops": 1}]}))
    out = _run(bad)
    assert out.returncode != 0 and "unknown fields ['oops']" in out.stderr
