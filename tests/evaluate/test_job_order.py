"""Evaluation runs one scene's jobs together, and its results come back in the order the jobs were built."""
from stages.evaluate.episodes import Job
from stages.evaluate.jobs import environment_groups, ungroup


def _job(policy: str, task: str, scene_id: int, split: str) -> Job:
    return Job(policy=policy, policy_path=f"{policy}.zip", tokenize_dir="tok", text_embeddings={}, task=task,
               scene={"scene_id": scene_id}, split=split, seeds=[scene_id], max_steps=3)


def _name(j: Job) -> str:
    return f"{j.policy}/{j.task}/{j.scene['scene_id']}/{j.split}"


def test_a_scenes_jobs_form_one_group_in_build_order_and_results_return_in_build_order():
    built = [_job(p, t, s, sp) for p in ("sft", "ppo", "ppo@128") for sp, scenes in (("ind", (3, 1)), ("ood", (7,)))
             for t in ("push", "pull") for s in scenes]
    groups = environment_groups(built)
    assert sorted(i for g in groups for i in g) == list(range(len(built)))
    assert len(groups) == 6  # (push, pull) x scenes (3, 1, 7)
    for g in groups:
        assert len({(built[i].task, built[i].scene["scene_id"], built[i].split) for i in g}) == 1  # one scene
        assert [built[i].policy for i in g] == ["sft", "ppo", "ppo@128"]  # the policies in build order
    done = [[f"result of {_name(built[i])}" for i in g] for g in groups]
    assert ungroup(done, groups) == [f"result of {_name(j)}" for j in built]
