"""scripts/replication_verdict.py: the pre-registered predictions read from hand-made episode files and
precisions give known verdicts; fewer than six seeds leave the decision pending; the world-model arm's
stem is found among the files whatever its method suffix; seeds from several builds of the store are
pooled, each paired within its own build; precision is read from the recorded file."""
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


def _files(folder: Path, seeds, wm_ood_wins: set[int], tag: str = "t", date: str = "2026-12-05") -> None:
    for s in seeds:
        for stem, policy, ind, ood in (("sft", "sft", {0}, {0}), ("replication-wm_gated", "ppo", {0}, wm_ood_wins),
                                       ("replication-rule", "ppo", {0, 1, 2, 3}, {0, 1})):
            _write(folder, f"{stem}_s{s}_{tag}_{date}.jsonl", policy, "ind", ind)
            _write(folder, f"{stem}_ood_s{s}_{tag}_{date}.jsonl", policy, "ood", ood)


def _run(folder: Path, store: Path) -> str:
    out = subprocess.run([sys.executable, str(SCRIPT), "--folder", str(folder), "--store", str(store)],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    return out.stdout


def _line(stdout: str, name: str) -> str:
    return next(line for line in stdout.splitlines() if line.split()[:1] == [name])


def test_six_seeds_of_a_winning_wm_arm_meet_the_decision_and_fail_predictions_1_and_3(tmp_path):
    _files(tmp_path, range(6), {0, 1, 2, 3})   # wm OOD: 4 of 4, SFT 1 of 4, rule 2 of 4
    out = _run(tmp_path, tmp_path / "store")
    assert "seeds with every file: 0 (t), 1 (t), 2 (t), 3 (t), 4 (t), 5 (t) of" in out
    assert "FAILS " in _line(out, "1") and "so far" not in out and "+0.750 [" in _line(out, "1")           # +0.75, far above +0.03
    assert "holds" in _line(out, "2") and "+0.750 [" in _line(out, "2")           # rule 4/4 vs SFT 1/4 IND
    assert "FAILS" in _line(out, "3") and "+0.500 [" in _line(out, "3")           # wm 4/4 vs rule 2/4 OOD
    assert "open" in _line(out, "4")                                               # an empty store, no file: no precision
    assert not (tmp_path / "replication_precision.json").exists()                  # nothing to record
    assert "MET" in _line(out, "decision") and "NOT MET" not in _line(out, "decision")


def test_missing_seeds_leave_the_decision_pending(tmp_path):
    _files(tmp_path, range(3), {0, 1, 2, 3})
    _write(tmp_path, "sft_s3_t_2026-12-05.jsonl", "sft", "ind", set())   # seed 3 half-written: not counted
    out = _run(tmp_path, tmp_path / "store")
    assert "seeds with every file: 0 (t), 1 (t), 2 (t) of" in out
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


def test_seeds_of_two_builds_pool_each_paired_within_its_build_and_recorded_precision_is_read(tmp_path):
    _files(tmp_path, range(3), {0, 1, 2, 3}, tag="a", date="2026-12-05")   # wm OOD 4/4 on build a
    _files(tmp_path, range(1, 6), {0}, tag="b", date="2026-12-06")         # wm OOD 1/4 on build b; seeds 1-2 again
    points = [{"tag": "a", "stem": "replication-wm_gated", "seed": 0, "split": "ind", "precision": 0.4},
              {"tag": "b", "stem": "replication-rule", "seed": 3, "split": "ood", "precision": 0.6}]
    (tmp_path / "replication_precision.json").write_text(json.dumps({"points": points}))
    out = _run(tmp_path, tmp_path / "store")
    assert "seeds with every file: 0 (a), 1 (a), 2 (a), 3 (b), 4 (b), 5 (b) of" in out  # build a finished 1, 2 first
    # 3 seeds at +0.75 and 3 at 0 against SFT out of domain: +0.375 pooled over 24 pairs
    assert "+0.375 [" in _line(out, "1") and "(n=24)" in _line(out, "1")
    assert "FAILS" in _line(out, "4") and "replication-rule s3 b ood 0.60" in _line(out, "4")
    assert json.loads((tmp_path / "replication_precision.json").read_text())["points"] == points  # left as it was


def test_a_seed_finished_on_two_builds_the_same_day_is_refused(tmp_path):
    _files(tmp_path, range(6), {0}, tag="a")
    _files(tmp_path, [2], {0}, tag="b")
    out = subprocess.run([sys.executable, str(SCRIPT), "--folder", str(tmp_path), "--store", str(tmp_path / "store")],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode != 0 and "seed 2 finished on two builds of the store the same day (a, b)" in out.stderr
