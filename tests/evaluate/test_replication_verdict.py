"""scripts/replication_verdict.py: the pre-registered predictions read from hand-made episode files and
precisions give known verdicts; fewer than six seeds leave the decision pending; the world-model arm's
stem is found among the files whatever its method suffix."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "scripts" / "replication_verdict.py"
sys.path.insert(0, str(REPO / "scripts"))

from replication_verdict import judge  # noqa: E402


def _write(folder: Path, name: str, policy: str, split: str, wins: set[int]) -> None:
    """Four initial states of one task; state i succeeds if i is in ``wins``."""
    rows = [{"policy": policy, "task": "push", "split": split, "scene_id": "a", "seed": i, "success": i in wins}
            for i in range(4)]
    (folder / name).write_text("".join(json.dumps(r) + "\n" for r in rows))


def _files(folder: Path, seeds, wm_ood_wins: set[int]) -> None:
    for s in seeds:
        for stem, policy, ind, ood in (("sft", "sft", {0}, {0}), ("replication-wm_gated", "ppo", {0}, wm_ood_wins),
                                       ("replication-rule", "ppo", {0, 1, 2, 3}, {0, 1})):
            _write(folder, f"{stem}_s{s}_t_2026-12-05.jsonl", policy, "ind", ind)
            _write(folder, f"{stem}_ood_s{s}_t_2026-12-05.jsonl", policy, "ood", ood)


def _run(folder: Path, store: Path) -> str:
    out = subprocess.run([sys.executable, str(SCRIPT), "--tag", "t", "--folder", str(folder), "--store", str(store)],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    return out.stdout


def _line(stdout: str, name: str) -> str:
    return next(line for line in stdout.splitlines() if line.split()[:1] == [name])


def test_six_seeds_of_a_winning_wm_arm_meet_the_decision_and_fail_predictions_1_and_3(tmp_path):
    _files(tmp_path, range(6), {0, 1, 2, 3})   # wm OOD: 4 of 4, SFT 1 of 4, rule 2 of 4
    out = _run(tmp_path, tmp_path / "store")
    assert "world-model arm replication-wm_gated; seeds with every file: 0, 1, 2, 3, 4, 5" in out
    assert "FAILS " in _line(out, "1") and "so far" not in out and "+0.750 [" in _line(out, "1")           # +0.75, far above +0.03
    assert "holds" in _line(out, "2") and "+0.750 [" in _line(out, "2")           # rule 4/4 vs SFT 1/4 IND
    assert "FAILS" in _line(out, "3") and "+0.500 [" in _line(out, "3")           # wm 4/4 vs rule 2/4 OOD
    assert "open" in _line(out, "4")                                               # an empty store: no precision
    assert "precision not read: the store's tag is c" in out                      # --tag t is another build's
    assert "MET" in _line(out, "decision") and "NOT MET" not in _line(out, "decision")


def test_missing_seeds_leave_the_decision_pending(tmp_path):
    _files(tmp_path, range(3), {0, 1, 2, 3})
    _write(tmp_path, "sft_s3_t_2026-12-05.jsonl", "sft", "ind", set())   # seed 3 half-written: not counted
    out = _run(tmp_path, tmp_path / "store")
    assert "seeds with every file: 0, 1, 2 of" in out
    assert "pending: 3 of 6 seeds" in _line(out, "decision")
    assert "FAILS so far" in _line(out, "1")                                       # +0.75 on three seeds


def test_predictions_as_written():
    level = {"diff": 0.01, "lo": -0.01, "hi": 0.03, "n": 2400}
    above = {"diff": 0.04, "lo": 0.01, "hi": 0.07, "n": 2400}
    r = {x.name: x.holds for x in judge(level, above, level, {"a s0 ind": 0.3, "a s0 ood": None}, tuple(range(6)))}
    assert r == {"1": True, "2": True, "3": False, "4": True, "decision": False}
    r = {x.name: x.holds for x in judge(above, level, {**level, "diff": 0.0}, {"a s0 ind": 0.5}, tuple(range(6)))}
    assert r == {"1": False, "2": False, "3": True, "4": False, "decision": True}
    r = {x.name: x.holds for x in judge(None, None, None, {}, ())}
    assert r == {"1": None, "2": None, "3": None, "4": None, "decision": None}
