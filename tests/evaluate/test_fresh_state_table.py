"""scripts/fresh_state_table.py: hand-made episode files give known paired differences, overall and
per task (``--by-task``, ``--group``); the committed manifest resolves to committed files that pair;
a malformed manifest or group names what is wrong."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "scripts" / "fresh_state_table.py"


def _write(folder: Path, name: str, policy: str, split: str, wins: set[int], tasks=("push",)) -> None:
    """Four initial states per task; state i of task k is episode 4k + i of ``wins``."""
    rows = [{"policy": policy, "task": t, "split": split, "scene_id": "a", "seed": i, "success": 4 * k + i in wins}
            for k, t in enumerate(tasks) for i in range(4)]
    (folder / name).write_text("".join(json.dumps(r) + "\n" for r in rows))


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=REPO)


def test_pooled_and_across_seed_differences_per_split(tmp_path):
    for seed, ind_wins, ood_wins in ((0, {0, 1, 2, 3}, {0}), (1, set(), {0})):
        _write(tmp_path, f"sft_s{seed}_m_2026-01-01.jsonl", "sft", "ind", set())
        _write(tmp_path, f"sft_ood_s{seed}_m_2026-01-01.jsonl", "sft", "ood", {0, 1})
        _write(tmp_path, f"meth_s{seed}_m_2026-01-02.jsonl", "ppo", "ind", ind_wins)
        _write(tmp_path, f"meth_ood_s{seed}_m_2026-01-02.jsonl", "ppo", "ood", ood_wins)
    # a file of another stem sharing the prefix must not be picked up
    _write(tmp_path, "meth_random_s0_m_2026-01-02.jsonl", "ppo", "ind", set())
    (tmp_path / "comparisons.json").write_text(json.dumps({"comparisons": [
        {"label": "meth", "stem": "meth", "baseline": "sft", "seeds": [0, 1], "tag": "m"}]}))
    out = _run("--manifest", str(tmp_path / "comparisons.json"), "--figure", str(tmp_path / "f.png"))
    assert out.returncode == 0, out.stderr
    row = next(line for line in out.stdout.splitlines() if line.startswith("| meth |"))
    # IND: seed 0 +1.00, seed 1 +0.00 -> pooled +0.50 over 8 pairs, sd 0.53, half-width 1.96 * 0.53 / sqrt(8) = 0.37;
    # across seeds sd 0.71, t(1) = 12.7 -> clipped to [-1, +1]
    # OOD: both seeds -0.25 (the method lost state 1) -> across seeds sd 0, interval of zero width
    assert "| +0.50 [+0.13, +0.87] | +0.50 [-1.00, +1.00] | -0.25 [-0.57, +0.07] | -0.25 [-0.25, -0.25] | 8 |" in row
    assert (tmp_path / "f.png").stat().st_size > 0
    both = _run("--manifest", str(tmp_path / "comparisons.json"), "--both-splits").stdout.splitlines()
    # 16 pairs: IND +4 (seed 0) and 0, OOD -1 and -1 -> +2 / 16 = +0.125
    assert "| meth | `sft` | 0, 1 | ind + ood | +0.125 [" in next(x for x in both if "ind + ood" in x)
    assert "| 4 / 2 | 16 |" in next(x for x in both if "ind + ood" in x)


def test_a_tag_per_seed_pairs_each_seed_within_its_own_build(tmp_path):
    for seed, tag in ((0, "a"), (1, "b")):
        _write(tmp_path, f"sft_s{seed}_{tag}_2026-01-01.jsonl", "sft", "ind", set())
        _write(tmp_path, f"meth_s{seed}_{tag}_2026-01-01.jsonl", "ppo", "ind", {0, 1, 2, 3} if tag == "a" else set())
    _write(tmp_path, "meth_s1_a_2026-01-01.jsonl", "ppo", "ind", {0, 1, 2, 3})  # seed 1 of build a: not listed, not read
    (tmp_path / "comparisons.json").write_text(json.dumps({"comparisons": [
        {"label": "meth", "stem": "meth", "baseline": "sft", "seeds": [0, 1], "tag": ["a", "b"], "splits": ["ind"]}]}))
    out = _run("--manifest", str(tmp_path / "comparisons.json"))
    assert out.returncode == 0, out.stderr
    row = next(line for line in out.stdout.splitlines() if line.startswith("| meth |"))
    assert "| +0.50 [+0.13, +0.87] |" in row  # seed 0 +1.00 (build a), seed 1 +0.00 (build b)


def test_committed_manifest_pairs_every_listed_file():
    out = _run("--by-task", "--group", "push+pull=push,pull")
    assert out.returncode == 0, out.stderr
    manifest = json.loads((REPO / "docs" / "results" / "fresh_states" / "comparisons.json").read_text())
    overall, per_task = out.stdout.strip().split("\n\n")
    rows = [line for line in overall.splitlines() if line.startswith("| ") and not line.startswith("| method")]
    assert len(rows) == len(manifest["comparisons"])
    # every comparison: a row for each of the four tasks and one for the group (RESULTS, "Where PPO ... gains")
    task_rows = [line for line in per_task.splitlines() if line.startswith("| ") and not line.startswith("| method")]
    assert len(task_rows) == 5 * len(manifest["comparisons"])


@pytest.mark.parametrize("manifest, message", [
    ({"comparisons": [{"label": "x", "stem": "meth", "baseline": "sft", "seeds": [0]}]}, "has fields"),
    ({"comparisons": [{"label": "x", "stem": "meth", "baseline": "sft", "seeds": [], "tag": "m"}]}, "non-empty list"),
    ({"comparisons": [{"label": "x", "stem": "meth", "baseline": "sft", "seeds": [0], "tag": "m", "splits": ["val"]}]},
     "not a subset"),
    ({"comparisons": [{"label": "x", "stem": "nothing", "baseline": "sft", "seeds": [0], "tag": "m"}]},
     "0 files match nothing_s0_m_<date>.jsonl"),
    ({"rows": []}, "expected {\"comparisons\""),
    ({"comparisons": [{"label": "x", "stem": "meth", "baseline": "sft", "seeds": [0, 1], "tag": ["m"]}]},
     "needs one non-empty tag per seed (2)"),
    ({"comparisons": [{"label": "x", "stem": "meth", "baseline": "sft", "seeds": [0], "tag": 3}]}, "tag must be"),
])
def test_bad_manifest_names_what_is_wrong(tmp_path, manifest, message):
    _write(tmp_path, "sft_s0_m_2026-01-01.jsonl", "sft", "ind", set())
    (tmp_path / "comparisons.json").write_text(json.dumps(manifest))
    out = _run("--manifest", str(tmp_path / "comparisons.json"))
    assert out.returncode != 0 and message in out.stderr, out.stderr


def test_by_task_rows_and_groups(tmp_path):
    tasks = ("push", "pull", "pick_place")
    for seed in (0, 1):
        for split in ("ind", "ood"):
            infix = "" if split == "ind" else "_ood"
            _write(tmp_path, f"sft{infix}_s{seed}_m_2026-01-01.jsonl", "sft", split, {0, 4, 8}, tasks)
            # push: +2 of 4 states; pull: unchanged; pick_place: -1 of 4
            _write(tmp_path, f"meth{infix}_s{seed}_m_2026-01-02.jsonl", "ppo", split, {0, 1, 2, 4}, tasks)
    (tmp_path / "comparisons.json").write_text(json.dumps({"comparisons": [
        {"label": "meth", "stem": "meth", "baseline": "sft", "seeds": [0, 1], "tag": "m"}]}))
    out = _run("--manifest", str(tmp_path / "comparisons.json"), "--by-task", "--group", "push+pull=push,pull")
    assert out.returncode == 0, out.stderr
    overall, per_task = out.stdout.strip().split("\n\n")  # the usual table, then the per-task one
    assert "| +0.08 [" in overall  # all tasks: (+2 + 0 - 1) / 12 per seed
    rows = {line.split(" | ")[3]: line for line in per_task.splitlines() if line.startswith("| meth | `sft` | 0, 1 | ")}
    assert list(rows) == ["push", "pull", "pick_place", "push+pull"]
    # every seed and split the same: across seeds sd 0, interval of zero width; pooled over 8 pairs per task
    assert "| +0.50 [+0.13, +0.87] | +0.50 [+0.50, +0.50] | +0.50 [+0.13, +0.87] | +0.50 [+0.50, +0.50] | 8 |" in rows["push"]
    assert "| +0.00 [+0.00, +0.00] | +0.00 [+0.00, +0.00] |" in rows["pull"]
    assert "| -0.25 [-0.57, +0.07] | -0.25 [-0.25, -0.25] |" in rows["pick_place"]
    # push and pull pooled: 16 pairs, mean +0.25
    assert rows["push+pull"].endswith("| 16 |") and "| +0.25 [" in rows["push+pull"]


@pytest.mark.parametrize("args, message", [
    (["--by-task", "--group", "push,pull"], "expected NAME=task,task"),
    (["--by-task", "--group", "both=push,lift"], "tasks ['lift'] are in no compared episode"),
    (["--group", "both=push"], "--group needs --by-task"),
])
def test_bad_group_names_what_is_wrong(tmp_path, args, message):
    _write(tmp_path, "sft_s0_m_2026-01-01.jsonl", "sft", "ind", set())
    _write(tmp_path, "meth_s0_m_2026-01-02.jsonl", "ppo", "ind", {0})
    (tmp_path / "comparisons.json").write_text(json.dumps({"comparisons": [
        {"label": "meth", "stem": "meth", "baseline": "sft", "seeds": [0], "tag": "m", "splits": ["ind"]}]}))
    out = _run("--manifest", str(tmp_path / "comparisons.json"), *args)
    assert out.returncode != 0 and message in out.stderr, out.stderr


def test_rates_print_each_policys_success_per_task_and_split_once(tmp_path):
    tasks = ("push", "pull")
    for seed in (0, 1):
        for split in ("ind", "ood"):
            infix = "" if split == "ind" else "_ood"
            _write(tmp_path, f"sft{infix}_s{seed}_m_2026-01-01.jsonl", "sft", split, {0, 4}, tasks)
            _write(tmp_path, f"meth{infix}_s{seed}_m_2026-01-02.jsonl", "ppo", split, {0, 1, 2, 3}, tasks)
    (tmp_path / "comparisons.json").write_text(json.dumps({"comparisons": [
        {"label": "meth", "stem": "meth", "baseline": "sft", "seeds": [0, 1], "tag": "m"},
        {"label": "meth again", "stem": "meth", "baseline": "sft", "seeds": [0, 1], "tag": "m"}]}))
    out = _run("--manifest", str(tmp_path / "comparisons.json"), "--rates")
    assert out.returncode == 0, out.stderr
    rates = out.stdout.strip().split("\n\n")[-1].splitlines()
    assert rates[0] == ("| policy | seeds | IND push | IND pull | IND all | OOD push | OOD pull | OOD all |")
    body = [line for line in rates[2:]]
    assert len(body) == 2  # each (stem, seeds) once, the baseline first
    # sft: 1 of 4 per task -> 0.25; 4 of 16 over both tasks and seeds
    assert body[0].startswith("| `sft` | 0, 1 | 0.25 | 0.25 | **0.25** [") and body[0].endswith("(n = 16) |")
    # meth: every push state, no pull state -> 1.00 / 0.00, 8 of 16 over all
    assert body[1].startswith("| `meth` | 0, 1 | 1.00 | 0.00 | **0.50** [0.28, 0.72] (n = 16) |")


def test_rest_prints_the_share_of_failed_and_successful_episodes_that_came_to_rest(tmp_path):
    def write(name, policy, split, rows):  # rows: (success, rest_steps or None) per state
        lines = [{"policy": policy, "task": "push", "split": split, "scene_id": "a", "seed": i, "success": ok,
                  **({} if rest is None else {"rest_steps": rest})} for i, (ok, rest) in enumerate(rows)]
        (tmp_path / name).write_text("".join(json.dumps(r) + "\n" for r in lines))

    write("sft_s0_m_2026-01-01.jsonl", "sft", "ind", [(False, 3), (False, 2), (True, 0), (True, 5)])
    write("meth_s0_m_2026-01-02.jsonl", "ppo", "ind", [(False, None), (True, None), (True, None), (True, None)])
    (tmp_path / "comparisons.json").write_text(json.dumps({"comparisons": [
        {"label": "meth", "stem": "meth", "baseline": "sft", "seeds": [0], "tag": "m", "splits": ["ind"]}]}))
    out = _run("--manifest", str(tmp_path / "comparisons.json"), "--rest")
    assert out.returncode == 0, out.stderr
    rest = out.stdout.strip().split("\n\n")[-1].splitlines()
    assert rest[0].startswith("| policy | seeds | IND failed that came to rest | IND succeeded that came to rest |")
    # sft: 1 of 2 failures rested 3 steps running (2 is too short), 1 of 2 successes; meth's file predates the field
    assert rest[2].startswith("| `sft` | 0 | 0.50 [") and "(1/2) | 0.50 [" in rest[2]
    assert rest[3] == "| `meth` | 0 | - | - | - | - |"


def test_rates_leave_out_a_files_rows_of_another_split(tmp_path):
    """Older files held both splits in the in-domain file: an IND-only comparison counts its IND rows."""
    _write(tmp_path, "sft_s0_m_2026-01-01.jsonl", "sft", "ind", {0})
    with (tmp_path / "sft_s0_m_2026-01-01.jsonl").open("a") as f:  # four OOD rows, all successes
        f.writelines(json.dumps({"policy": "sft", "task": "push", "split": "ood", "scene_id": "a", "seed": i,
                                 "success": True}) + "\n" for i in range(4))
    _write(tmp_path, "meth_s0_m_2026-01-02.jsonl", "ppo", "ind", {0, 1})
    (tmp_path / "comparisons.json").write_text(json.dumps({"comparisons": [
        {"label": "meth", "stem": "meth", "baseline": "sft", "seeds": [0], "tag": "m", "splits": ["ind"]}]}))
    out = _run("--manifest", str(tmp_path / "comparisons.json"), "--rates")
    assert out.returncode == 0, out.stderr
    sft = next(line for line in out.stdout.splitlines() if line.startswith("| `sft` |"))
    assert "(1/4)" not in sft and "**0.25** [" in sft and "(n = 4) | - | - |" in sft
