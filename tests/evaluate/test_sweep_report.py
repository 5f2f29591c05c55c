"""The sweep report on known, hand-written point artifacts: pooled counts, SFT counted once per seed,
per-run rates, costs and figures."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages.evaluate.report import write_gif
from stages.rl import method_of
from stages.sweep_report import report

TASKS = ["push", "pull"]


def _point(root: Path, reward: str, seed: int, ppo_wins: int, sft_wins: int, snap_wins: int,
           evaluated: bool = True, tasks: list[str] = TASKS, rule_terms: str = "success",
           rl_json: dict | None = None) -> dict:
    """A committed rl (and evaluate) artifact: 4 episodes per (policy, split), tasks alternating.
    ``rl_json`` replaces what the rl stage publishes (an older artifact's)."""
    rl = root / f"rl-{reward}-{rule_terms}-{seed}"
    (rl / "snapshots").mkdir(parents=True)
    (rl / "manifest.json").write_text(json.dumps({"duration_s": 100.0 + seed, "key_inputs": {
        "config": {"seed": seed, "reward": reward, "tasks": tasks}}}))
    facts = {"reward": reward, "success_payout": True, "rule_terms": rule_terms if reward == "rule" else None,
             "method": method_of(reward, rule_terms)}
    (rl / "rl.json").write_text(json.dumps(facts if rl_json is None else rl_json))
    metrics = {"ppo/seconds": 50.0, "ppo/env_steps_per_second": 40.0, "ppo/terminated_fraction": 0.1,
               "diagnostics/ind/wm/spearman_progress": 0.5 + seed / 10}
    if seed == 0:  # what the rl stage writes since it bins training success by start step; seed 1 is older
        metrics.update({"ppo/success_first_fifth": 0.4, "ppo/success_last_fifth": 0.6})
        # and, with rl.accept_episodes, its acceptance test: here PPO failed it and SFT's weights shipped
        metrics.update({"accept/kept_ppo": False, "accept/difference": -0.08, "accept/episodes": 600})
        (rl / "success_by_start.json").write_text(json.dumps({"unfinished_from": 30, "bins": [
            {"start_from": 0, "start_to": 15, "episodes": 5, "success": 0.4, "interval": [0.1, 0.8]},
            {"start_from": 15, "start_to": 30, "episodes": 5, "success": 0.6, "interval": [0.2, 0.9]}]}))
    (rl / "metrics.json").write_text(json.dumps(metrics))
    (rl / "snapshots" / "index.json").write_text(json.dumps([{"timesteps": 100, "wall_seconds": 10.0 + seed}]))
    (rl / "episodes.json").write_text(json.dumps([{"t": i, "wall": float(i), "return": float(i % 3), "length": 5,
                                                   "terminated": False} for i in range(30)]))
    sft = root / f"sft-{seed}-{'-'.join(tasks)}"  # one SFT policy per (seed, tasks), shared by the rewards
    if not sft.is_dir():
        sft.mkdir()
        (sft / "manifest.json").write_text(json.dumps({"duration_s": 30.0}))
        (sft / "policy.json").write_text(json.dumps({"tasks": tasks, "frame_skip": 4}))
    arts = {"rl": rl, "sft": sft}
    if evaluated:
        ev = root / f"ev-{reward}-{rule_terms}-{seed}"
        ev.mkdir()
        (ev / "manifest.json").write_text(json.dumps({"duration_s": 20.0}))
        rows = []
        for policy, wins in (("sft", sft_wins), ("ppo", ppo_wins), ("ppo@100", snap_wins)):
            for split in ("ind", "ood"):
                for i in range(4):
                    rows.append({"policy": policy, "task": tasks[i % len(tasks)], "split": split, "seed": i,
                                 "success": i < wins, "steps": 10, "instruction": "x"})
        (ev / "results.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
        # the evaluate stage's GIF names: one per task since it records each task's first episode; seed 1 older
        names = (f"rollout_ppo_ind_{tasks[0]}.gif", f"rollout_sft_ood_{tasks[0]}.gif") if seed == 0 else \
            ("rollout_ppo_ind.gif", "rollout_sft_ood.gif")
        for name in names:
            write_gif(np.random.default_rng(seed).integers(0, 255, (3, 8, 8, 3), dtype=np.uint8), ev / name)
        (ev / "extreme_actions.png").write_bytes(b"\x89PNG")  # only copied
        arts["evaluate"] = ev
    return {"values": {"rl.reward": reward, "rl.seed": seed}, "label": f"{reward}/{seed}", "artifacts": arts}


def test_pooled_counts_sft_once_per_seed_and_figures(tmp_path):
    points = [_point(tmp_path, "wm", 0, ppo_wins=1, sft_wins=2, snap_wins=0),
              _point(tmp_path, "wm", 1, ppo_wins=3, sft_wins=1, snap_wins=2),
              _point(tmp_path, "rule", 0, ppo_wins=4, sft_wins=2, snap_wins=4),
              _point(tmp_path, "rule", 1, ppo_wins=0, sft_wins=1, snap_wins=0, evaluated=False)]
    out = tmp_path / "out"
    out.mkdir()
    md = report(points, out).read_text()
    table = md.split("## PPO minus SFT")[0]  # the pooled success table comes first
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines() if line.startswith("| ")}
    # wm: 1 + 3 of 8 IND (two seeds pooled); push gets the even-indexed wins: seed 0 -> 1 of 2, seed 1 -> 2 of 2
    assert "0.50 [0.22, 0.78] (4/8)" in rows["PPO in world model (WM reward, ours)"]
    assert "(3/4)" in rows["PPO in world model (WM reward, ours)"]
    # rule: only seed 0 was evaluated
    assert "1.00 [0.51, 1.00] (4/4)" in rows["PPO in ManiSkill (rule reward: success alone)"]
    # SFT: seeds 0 and 1 once each (not once per point): 2 + 1 of 8
    assert "(3/8)" in rows["Supervised finetune (SFT)"] and "(5/12)" not in rows["Supervised finetune (SFT)"]
    assert "Table 2 layout" in md and "Table 1 layout" not in md
    assert "0.250 / 0.750" in md  # per-run wm IND rates
    assert "100 / 101" in md  # rl stage seconds of the two wm seeds
    assert "ind/wm/spearman_progress | 4 of 4 | 0.550" in md
    assert "| 0.40 -> 0.60 / - |" in md  # wm's training success by start fifth: seed 0's, seed 1 has none
    assert "| SFT (-0.08, 600 sim episodes) / - |" in md  # seed 0 shipped SFT's weights; seed 1 had no test
    for name in ("success_vs_time.png", "training_curves.png", "rollout_wm_ind.gif", "rollout_sft_ood.gif",
                 "extreme_actions.png", "rollouts.png", "report.html"):
        assert (out / name).is_file(), name
        assert name in md or name == "report.html"


def test_rule_rows_follow_what_the_rule_reward_paid(tmp_path):
    """Success-only and dense rule runs are separate rows; an older rl.json (no method) reads as dense."""
    points = [_point(tmp_path, "rule", 0, ppo_wins=4, sft_wins=2, snap_wins=0),
              _point(tmp_path, "rule", 0, ppo_wins=1, sft_wins=2, snap_wins=0, rule_terms="dense"),
              _point(tmp_path, "rule", 1, ppo_wins=2, sft_wins=1, snap_wins=0, rule_terms="old",
                     rl_json={"reward": "rule", "success_payout": True})]
    out = tmp_path / "out"
    out.mkdir()
    table = report(points, out).read_text().split("## PPO minus SFT")[0]
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines() if line.startswith("| ")}
    assert "(4/4)" in rows["PPO in ManiSkill (rule reward: success alone)"]
    assert "(3/8)" in rows["PPO in ManiSkill (rule reward: the task's dense reward)"]  # 1 + 2 of 8 IND


def test_single_task_points_make_table_1(tmp_path):
    points = [_point(tmp_path, "wm", 0, ppo_wins=2, sft_wins=0, snap_wins=0, tasks=["push"])]
    out = tmp_path / "out"
    out.mkdir()
    md = report(points, out).read_text()
    assert "Table 1 layout: one policy per task" in md and "Table 2" not in md


def test_no_committed_point_writes_a_clear_empty_report(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    md = report([{"values": {}, "label": "p", "artifacts": {"rl": tmp_path / "missing"}}], out).read_text()
    assert "No point has a committed rl artifact yet" in md


def test_paired_differences_match_episodes_by_initial_state():
    from stages.sweep_report.paired import pair_up, paired_difference

    sft = [{"task": "push", "split": "ind", "scene_id": "a", "seed": i, "success": i < 2} for i in range(4)]
    ppo = [{"task": "push", "split": "ind", "scene_id": "a", "seed": i, "success": i != 0} for i in reversed(range(4))]
    ppo.append({"task": "push", "split": "ind", "scene_id": "b", "seed": 0, "success": True})  # SFT never ran it
    pairs = pair_up(ppo, sft)
    assert len(pairs) == 4  # by initial state, not by order; the unmatched episode is left out
    res = paired_difference([(bool(r["success"]), base) for r, base in pairs])
    # differences: seed 0: 0-1, seed 1: 1-1, seeds 2 and 3: 1-0 -> mean 0.25, sd 0.957, half-width 0.938
    assert res["n"] == 4 and res["better"] == 2 and res["worse"] == 1
    assert abs(res["diff"] - 0.25) < 1e-9 and abs(res["lo"] - (0.25 - 0.938)) < 1e-3 and res["hi"] == 1.0
    assert paired_difference([])["n"] == 0


def test_the_paired_section_reports_ppo_minus_its_own_sft(tmp_path):
    points = [_point(tmp_path, "rule", 0, ppo_wins=4, sft_wins=0, snap_wins=0),
              _point(tmp_path, "rule", 1, ppo_wins=1, sft_wins=1, snap_wins=0)]
    out = tmp_path / "out"
    out.mkdir()
    md = report(points, out).read_text()
    section = md.split("## PPO minus SFT, paired on the same initial states")[1].split("## ")[0]
    rows = [line for line in section.splitlines() if line.startswith("| PPO in ManiSkill")]
    assert len(rows) == 4  # seed 0, seed 1, pooled, across seeds
    assert "+1.00 [+1.00, +1.00] (n=4, 4 better / 0 worse)" in rows[0]  # every state: PPO solved, SFT did not
    assert "+0.00 [+0.00, +0.00] (n=4, 0 better / 0 worse)" in rows[1]
    assert "+0.50" in rows[2] and "n=8, 4 better / 0 worse" in rows[2]
    # seeds +1.00 and +0.00: mean 0.5, sd 0.707, t(1) 12.71 -> half-width 6.35, clipped to [-1, 1]
    assert "across seeds" in rows[3] and "+0.50 [-1.00, +1.00] (2 seeds, sd 0.71)" in rows[3]


def test_the_per_task_section_splits_the_paired_differences_and_keeps_the_gated_arm_apart(tmp_path):
    points = [_point(tmp_path, "rule", 0, ppo_wins=4, sft_wins=0, snap_wins=0),
              _point(tmp_path, "rule", 1, ppo_wins=1, sft_wins=1, snap_wins=0),
              _point(tmp_path, "wm", 0, ppo_wins=0, sft_wins=0, snap_wins=0,
                     rl_json={"reward": "wm", "success_payout": True, "rule_terms": None, "method": "wm_gated"})]
    out = tmp_path / "out"
    out.mkdir()
    md = report(points, out).read_text()
    section = md.split("## PPO minus SFT per task, paired")[1].split("## ")[0]
    rule = {line.split(" | ")[1]: line for line in section.splitlines() if line.startswith("| PPO in ManiSkill")}
    assert list(rule) == ["push", "pull"]  # tasks alternate over the states: 0, 2 push; 1, 3 pull
    for row in rule.values():
        # seed 0: both of the task's states +1; seed 1: 0 -> pooled +0.50 over 4, across seeds +0.50 [-1, +1]
        assert "+0.50" in row and "n=4, 2 better / 0 worse" in row and "+0.50 [-1.00, +1.00] (2 seeds, sd 0.71)" in row
    gated = [line for line in section.splitlines() if line.startswith("| PPO in world model (WM reward, ours), calibration-gated")]
    assert len(gated) == 2 and all("+0.00 [+0.00, +0.00] (n=2, 0 better / 0 worse)" in line for line in gated)


def test_across_seeds_is_a_student_t_interval_over_the_seeds():
    from stages.sweep_report.paired import across_seeds, fmt_across_seeds

    res = across_seeds([0.1, 0.2, 0.3])  # mean 0.2, sd 0.1, t(2) = 4.303 -> half-width 0.248
    assert abs(res["diff"] - 0.2) < 1e-9 and abs(res["sd"] - 0.1) < 1e-9 and res["k"] == 3
    assert abs(res["lo"] - (0.2 - 0.2484)) < 1e-3 and abs(res["hi"] - (0.2 + 0.2484)) < 1e-3
    assert fmt_across_seeds(res) == "+0.20 [-0.05, +0.45] (3 seeds, sd 0.10)"
    assert fmt_across_seeds(across_seeds([0.4])) == "-" and across_seeds([])["k"] == 0


def test_paired_success_script_prints_pooled_and_across_seed_intervals(tmp_path):
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[2]

    def write(name, policy, wins):
        rows = [{"policy": policy, "task": "push", "split": "ind", "scene_id": "a", "seed": i, "success": i in wins}
                for i in range(4)]
        (tmp_path / name).write_text("".join(json.dumps(r) + "\n" for r in rows))
        return str(tmp_path / name)

    sft = [write(f"sft{s}.jsonl", "sft", set()) for s in (0, 1)]
    ppo = [write("ppo0.jsonl", "ppo", {0, 1, 2, 3}), write("ppo1.jsonl", "ppo", set())]
    out = subprocess.run([sys.executable, str(repo / "scripts" / "paired_success.py"), "--sft", *sft, "--", *ppo],
                         capture_output=True, text=True, check=True).stdout
    pooled = out.split("pooled:")[1]
    assert "ind   +0.50" in pooled and "(n=8, 4 better / 0 worse)" in pooled
    assert "+0.50 [-1.00, +1.00] (2 seeds, sd 0.71)" in out.split("across seeds")[1]
