"""Run/skip decisions of the real CLI on the six-stage test pipeline."""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from collections import Counter

from tests.engine.conftest import REPO

ALL = ["collect", "tokenize", "train_wm", "goals", "rl", "evaluate"]


def test_dag_of_the_shipped_pipeline_lists_eight_stages_in_order():
    out = subprocess.run([sys.executable, "-m", "pipeline", "dag"], cwd=REPO, capture_output=True, text=True, check=True).stdout
    names = [line.split()[1] for line in out.splitlines() if line.strip()]
    assert names == ["collect", "tokenize", "train_wm", "goals", "sft", "wm_play", "rl", "evaluate"]


def test_dag_dot(ws):
    out = ws.cli("dag", "--dot").stdout
    assert out.startswith("digraph") and '"rl" -> "evaluate";' in out


def _result(ws, stage: str) -> dict:
    (d,) = [p for p in (ws.store / stage).glob("*/*") if (p / "result.json").is_file()]
    return json.loads((d / "result.json").read_text())


def test_a_stage_draws_the_same_after_other_stages_as_alone(ws):
    # each node in a fresh process: a cache an earlier stage filled (built with random draws) would
    # otherwise shift what this stage draws after seeding (sft trained another policy after train_wm)
    ws.cli("run", "--until", "goals")
    pids = [line.split()[1] for line in ws.exec_log.read_text().splitlines()]
    assert len(set(pids)) == 4
    after_others = _result(ws, "goals")["draw"]
    ws.cli("run", "--only", "goals", "--force", "goals")
    assert _result(ws, "goals")["draw"] == after_others


def test_first_run_executes_all_second_none(ws):
    ws.cli("run")
    assert ws.executions() == ALL
    ws.reset_log()
    second = ws.cli("run")
    assert ws.executions() == []
    for s in ALL:
        assert f"{s}" in second.stderr
    assert second.stderr.count("cached") == 6
    status = ws.cli("status").stdout
    assert all(line.endswith("cached") for line in status.splitlines()[1:])


def test_config_change_reruns_stage_and_descendants_only(ws):
    ws.cli("run")
    ws.reset_log()
    st = ws.cli("status", "--set", "goals.value=40").stdout
    assert "config changed: goals.value" in st and "input changed: goals" in st
    ws.cli("run", "--set", "goals.value=40")
    assert ws.executions() == ["goals", "rl", "evaluate"]


def test_profile_and_yaml_edit_rerun_only_what_changed(ws):
    ws.cli("run")
    ws.reset_log()
    ws.spec.write_text(ws.spec.read_text().replace("config: {value: 6}", "config: {value: 60}"))
    ws.cli("run")
    assert ws.executions() == ["evaluate"]
    ws.reset_log()
    ws.cli("run", "--profile", "small")  # small does not override collect.value=10 -> collect changes
    assert ws.executions() == ALL


def test_equivalent_configs_share_a_key(ws):
    ws.cli("run")
    ws.reset_log()
    ws.cli("run", "--set", "rl.value=5", "--set", "rl.seed=0")  # the values already in effect
    assert ws.executions() == []


def test_editing_a_stage_source_reruns_it_and_descendants_only(ws):
    ws.cli("run")
    ws.reset_log()
    src = ws.root / "ts" / "train_wm.py"
    src.write_text(src.read_text() + "\n# an edit\n")
    st = ws.cli("status").stdout
    assert "train_wm" in st and "code changed" in st
    ws.cli("run")
    assert ws.executions() == ["train_wm", "goals", "rl", "evaluate"]


def test_editing_a_shared_helper_reruns_every_stage_that_imports_it(ws):
    ws.cli("run")
    ws.reset_log()
    helper = ws.root / "ts" / "common.py"
    helper.write_text(helper.read_text() + "\n# an edit\n")
    ws.cli("run")
    assert ws.executions() == ALL


def test_until_runs_the_stage_and_its_ancestors_only(ws):
    ws.cli("run", "--until", "train_wm")
    assert ws.executions() == ["collect", "tokenize", "train_wm"]
    ws.reset_log()
    ws.cli("run", "--until", "evaluate")
    assert ws.executions() == ["goals", "rl", "evaluate"]


def test_only_and_from(ws):
    bad = ws.cli("run", "--only", "tokenize", check=False)
    assert bad.returncode == 2 and "'collect' is needed but not cached" in bad.stderr
    assert ws.executions() == []
    ws.cli("run", "--until", "goals")
    ws.reset_log()
    ws.cli("run", "--from", "rl")
    assert ws.executions() == ["rl", "evaluate"]
    ws.reset_log()
    ws.cli("run", "--only", "rl", "--force", "rl")
    assert ws.executions() == ["rl"]


def test_force_reruns_a_cached_stage_and_keeps_its_key(ws):
    ws.cli("run")
    key = json.loads(ws.cli("show", "rl").stdout.split("\n", 3)[3])["key"]
    ws.reset_log()
    ws.cli("run", "--force", "rl")
    assert ws.executions() == ["rl"]
    assert json.loads(ws.cli("show", "rl").stdout.split("\n", 3)[3])["key"] == key


def test_sweep_runs_shared_ancestors_once_and_tabulates_twelve_points(ws):
    out = ws.cli("sweep", "rewards")
    counts = Counter(ws.executions())
    assert counts == {"collect": 1, "tokenize": 1, "train_wm": 1, "goals": 1, "rl": 12, "evaluate": 12}
    tables = list((ws.store / "sweeps" / "rewards").glob("*/results.json"))
    assert len(tables) == 1
    table = json.loads(tables[0].read_text())
    assert len(table["rows"]) == 12
    assert {(r["rl.reward"], r["rl.seed"]) for r in table["rows"]} == {
        (r, s) for r in ["wm", "rule", "embedding", "proxy"] for s in [0, 1, 2]}
    assert all(r["score"] == r["total"] * 10 for r in table["rows"])  # evaluate's own seed stays 0
    assert "| rl.reward | rl.seed |" in out.stdout
    report = (tables[0].parent / "report.txt").read_text().splitlines()
    assert len(report) == 12 and all(line.endswith(" 55") for line in report)  # the hook saw every point
    ws.reset_log()
    again = ws.cli("sweep", "rewards")
    assert ws.executions() == [] and again.returncode == 0


def test_axis_option_narrows_a_sweep(ws):
    status = ws.cli("status", "--sweep", "rewards", "--axis", "rl.seed=[0, 1]", "--axis", "rl.reward=[wm, rule]")
    assert status.stdout.count("sweep:rewards:") == 4
    ws.cli("sweep", "rewards", "--axis", "rl.seed=[1]", "--until", "rl")
    assert Counter(ws.executions())["rl"] == 4
    table = json.loads(next((ws.store / "sweeps" / "rewards").glob("*/results.json")).read_text())
    assert {(r["rl.reward"], r["rl.seed"]) for r in table["rows"]} == {(r, 1) for r in ["wm", "rule", "embedding", "proxy"]}


def test_sweep_with_jobs_uses_a_process_pool(ws):
    # each rl point takes a second, so the second worker gets work even when the first one started early
    ws.cli("sweep", "rewards", "--until", "rl", "--jobs", "2", TEST_SLEEP_STAGE="rl", TEST_SLEEP="1")
    pids, jobs = {}, {}
    for line in ws.exec_log.read_text().splitlines():
        stage, pid, n = line.split()
        pids.setdefault(stage, set()).add(pid)
        jobs.setdefault(stage, set()).add(int(n))
    assert len(pids["rl"]) >= 2  # the 12 rl points ran on more than one worker process
    assert jobs["rl"] == {1}  # ... and split the cores
    assert Counter(ws.executions())["rl"] == 12


def test_a_wave_of_different_stages_runs_them_in_turn_with_every_core(ws):
    # goals now needs only tokenize, so train_wm and goals are ready together: a short stage beside a
    # long one must not leave the long one on a single core after the short one ends
    ws.spec.write_text(ws.spec.read_text().replace("needs: [train_wm], config: {value: 4}",
                                                   "needs: [tokenize], config: {value: 4}"))
    ws.cli("run", "--jobs", "2")
    runs = [line.split() for line in ws.exec_log.read_text().splitlines()]
    assert {r[0] for r in runs} == {"collect", "tokenize", "train_wm", "goals", "rl", "evaluate"}
    assert all(r[2] == "2" for r in runs), runs


def test_stage_fan_out_with_ctx_map(ws):
    ws.cli("run", "--until", "collect", "--set", "collect.shards=4", "--jobs", "2")
    key_dir = next((ws.store / "collect").glob("*/*"))
    assert json.loads((key_dir / "result.json").read_text())["shards"] == [0, 1, 4, 9]


def test_status_and_run_record(ws):
    ws.cli("run", "--until", "tokenize")
    records = list((ws.store / "runs").glob("*.json"))
    assert len(records) == 1
    rec = json.loads(records[0].read_text())
    assert [n["stage"] for n in rec["nodes"]] == ["collect", "tokenize"]
    assert all(n["action"] == "ran" and n["reasons"] == ["missing"] for n in rec["nodes"])
    art = next((ws.store / "tokenize").glob("*/*"))
    assert (art / "log.txt").read_text().count("total 12") == 1  # the stage's log is kept in its artifact


def test_show_prints_manifest_and_verifies(ws):
    ws.cli("run", "--until", "collect")
    out = ws.cli("show", "collect", "--verify").stdout
    assert "state: ok" in out and "verify: ok" in out and '"result.json"' in out
    art = next((ws.store / "collect").glob("*/*"))
    (art / "result.json").write_text((art / "result.json").read_text().replace("10", "11"))  # same size
    bad = ws.cli("show", "collect", "--verify", check=False)
    assert bad.returncode == 1 and "result.json: content differs" in bad.stdout


def test_a_tied_axis_sets_several_paths_to_one_value_per_point(ws):
    spec = ws.spec.read_text().replace("      rl.seed: [0, 1, 2]", "      goals.value+rl.seed: [0, 1]")
    ws.spec.write_text(spec)
    ws.cli("sweep", "rewards", "--axis", "rl.reward=[wm]")
    assert Counter(ws.executions())["goals"] == 2 and Counter(ws.executions())["rl"] == 2  # 2 points, not 2 x 2
    ws.reset_log()
    ws.cli("sweep", "rewards", "--axis", "rl.reward=[wm]", "--axis", "rl.seed=[1]")  # a path names its tied axis
    assert ws.executions() == []
    bad = ws.cli("sweep", "rewards", "--axis", "rl.value=[1]", check=False)
    assert bad.returncode == 2 and "not an axis of sweep" in bad.stderr


def test_a_stage_that_reads_fewer_inputs_neither_waits_for_nor_keys_on_the_rest(ws):
    """``unread_needs``: rl not reading goals plans no goals, and goals' config does not re-key it."""
    st = ws.cli("status", "--until", "rl", "--set", "rl.skips=[goals]").stdout
    assert "goals" not in st and "rl" in st
    ws.cli("run", "--until", "rl", "--set", "rl.skips=[goals]")
    assert ws.executions() == ["collect", "tokenize", "train_wm", "rl"]
    assert _result(ws, "rl")["inputs"] == ["train_wm"]
    ws.reset_log()
    ws.cli("run", "--until", "rl", "--set", "rl.skips=[goals]", "--set", "goals.value=40")
    assert ws.executions() == []  # goals is not read: its change neither runs it nor re-keys rl
    ws.cli("run", "--until", "rl")  # the declared needs: goals runs now, and rl with it under a new key
    assert ws.executions() == ["goals", "rl"]
    ws.reset_log()
    ws.cli("run", "--set", "rl.skips=[goals]")  # the whole DAG: evaluate reads rl, rl reads no goals
    assert ws.executions() == ["evaluate"]  # the rl artifact that read train_wm alone is still the cached one


def test_dag_marks_the_needs_a_config_does_not_read(ws):
    lines = {line.split()[1]: line for line in ws.cli("dag").stdout.splitlines()}
    assert lines["rl"].endswith("<- goals, train_wm") and "unread" not in lines["rl"]
    lines = {line.split()[1]: line for line in ws.cli("dag", "--set", "rl.skips=[goals]").stdout.splitlines()}
    assert lines["rl"].endswith("<- train_wm  (declared, unread under this config: goals)")
    dot = ws.cli("dag", "--dot", "--set", "rl.skips=[goals]").stdout
    assert '"goals" -> "rl" [style=dashed, label="unread"];' in dot and '"train_wm" -> "rl";' in dot


def test_unread_needs_outside_the_declared_needs_is_a_clear_error(ws):
    proc = ws.cli("run", "--until", "rl", "--set", "rl.skips=[collect]", check=False)
    assert proc.returncode != 0
    assert "stage 'rl': unread_needs names 'collect', which pipeline.yaml does not list in stages.rl.needs" in proc.stderr
    assert ws.executions() == []


def test_the_manifest_names_the_machine_that_built_the_artifact(ws):
    # a key names the computation, not its bytes: another CPU kind may build other floats (pipeline.machine)
    ws.cli("run", "--until", "collect")
    out = ws.cli("show", "collect").stdout
    manifest = json.loads(out[out.index("{"):])
    machine = manifest["machine"]
    assert machine["cpu"] and machine["cpu"] != "unknown"
    assert machine["cores"] == os.cpu_count() and machine["python"] == platform.python_version()
