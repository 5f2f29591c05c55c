"""scripts/flip_strips.py: which paired states it picks to look at (the rerun itself runs in the e2e
test on the toy store's policies)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))

from flip_strips import pick  # noqa: E402


def _rows(policy: str, wins: dict[str, set[int]]) -> list[dict]:
    return [{"policy": policy, "task": t, "split": "ood", "scene_id": "s", "seed": i, "success": i in w}
            for t, w in wins.items() for i in range(6)]


def test_states_are_picked_by_kind_round_robin_over_tasks():
    method = _rows("ppo", {"push": {0, 1, 2, 3}, "pull": {0, 1}})
    base = _rows("sft", {"push": {4}, "pull": {0, 1, 5}})
    got = pick(method, base, per_way=3, same=1)
    # gained: push 0-3 (4 states), pull none; lost: push 4, pull 5; both won: pull 0, 1; both lost: push 5, pull 2-4
    assert got["gained"] == [("push", "ood", "s", 0), ("push", "ood", "s", 1), ("push", "ood", "s", 2)]
    assert got["lost"] == [("push", "ood", "s", 4), ("pull", "ood", "s", 5)]
    assert got["both_won"] == [("pull", "ood", "s", 0)]
    assert got["both_lost"] == [("push", "ood", "s", 5)]
    assert pick(method, base, per_way=0, same=0) == {"gained": [], "lost": [], "both_won": [], "both_lost": []}


def test_files_of_other_states_and_ppo_without_its_artifact_are_refused(tmp_path):
    import json

    def write(name, rows):
        (tmp_path / name).write_text("".join(json.dumps(r) + "\n" for r in rows))
        return str(tmp_path / name)

    ppo = write("ppo.jsonl", _rows("ppo", {"push": {0}}))
    sft = write("sft.jsonl", [{**r, "seed": r["seed"] + 100} for r in _rows("sft", {"push": {0}})])
    run = lambda *a: subprocess.run([sys.executable, str(REPO / "scripts" / "flip_strips.py"), "c", "t", "s", *a],  # noqa: E731
                                    capture_output=True, text=True, cwd=REPO)
    out = run("--method", ppo, "--baseline", sft)
    assert out.returncode != 0 and "holds PPO episodes: give its rl artifact (--method-rl)" in out.stderr
    out = run("--method", ppo, "--method-rl", str(tmp_path), "--baseline", sft)
    assert out.returncode != 0 and "share no initial state" in out.stderr
