"""scripts/evaluate_sft.py after a kill: whole jobs kept from F.partial, the rest run again."""
import json
import sys
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from evaluate_sft import append_rows, pending, read_partial  # noqa: E402


def job(task, scene, seeds, split="ind", policy="sft"):
    return SimpleNamespace(policy=policy, task=task, scene={"scene_id": scene}, split=split, seeds=seeds)


def rows(j, success=True):
    return [{"policy": j.policy, "task": j.task, "scene_id": j.scene["scene_id"], "split": j.split, "seed": s,
             "success": success, "steps": 7} for s in j.seeds]


def test_whole_jobs_are_kept_and_a_torn_or_half_written_job_runs_again(tmp_path):
    jobs = [job("push", "s0", [1, 2]), job("pull", "s1", [3, 4]), job("push", "s0", [1, 2], split="ood"), job("aim", "s2", [5])]
    path = tmp_path / "r.jsonl.partial"
    assert read_partial(path, jobs) == [] and pending(jobs, []) == jobs
    append_rows(path, rows(jobs[0]))
    append_rows(path, rows(jobs[2], success=False))
    with open(path, "a") as f:  # a kill in the middle of the next job's write: one whole row, one torn
        f.write(json.dumps(rows(jobs[1])[0]) + "\n" + json.dumps(rows(jobs[1])[1])[:20])
    kept = read_partial(path, jobs)
    assert kept == rows(jobs[0]) + rows(jobs[2], success=False)
    assert pending(jobs, kept) == [jobs[1], jobs[3]]
    # the file now holds whole lines only, so the next append starts on its own line
    append_rows(path, rows(jobs[3]))
    again = read_partial(path, jobs)
    assert again == kept + rows(jobs[3]) and pending(jobs, again) == [jobs[1]]
    # rows of another policy or split are not mistaken for this job's
    assert pending([job("push", "s0", [1, 2], policy="ppo")], again) == [job("push", "s0", [1, 2], policy="ppo")]
