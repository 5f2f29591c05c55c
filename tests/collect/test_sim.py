"""The task envs, the planner and delta-EE replay in the simulator (one env per task, reused)."""
import numpy as np
import pytest

pytestmark = pytest.mark.sim

from stages.collect.envs import DEFAULT_SCENE  # noqa: E402  (sets up Vulkan, then imports sapien)
from stages.collect.execute import replay  # noqa: E402
from stages.collect.sim import TASKS, get_scene, make_task_env  # noqa: E402
from stages.collect.worker import _sim, record_episode  # noqa: E402

SCENES = {  # a mix of shapes and both containers
    "pick_place": "small-red-cube__bowl__wood",
    "push": "large-blue-cylinder__plate__dark-grey",
    "pull": "small-green-sphere__bowl__wood",
    "move_to_aim": "large-yellow-capsule__plate__wood",
}


def _scene(task):
    return get_scene(SCENES[task]).to_dict()


@pytest.fixture(scope="module")
def sims():
    return {t: _sim(t, 64, "lowpoly", 400) for t in TASKS}


@pytest.mark.parametrize("task", TASKS)
def test_env_resets_and_steps(sims, task):
    env, _, state = sims[task]
    obs, info = env.reset(seed=0, options=dict(reconfigure=True, scene=_scene(task)))
    state["scene_id"] = SCENES[task]
    for _ in range(3):
        obs, reward, *_ , info = env.step(np.zeros((1, 7), np.float32))
    assert obs["sensor_data"]["third"]["rgb"].shape == (1, 64, 64, 3)
    assert obs["sensor_data"]["wrist"]["rgb"].shape == (1, 64, 64, 3)
    assert 0.0 <= float(reward) <= 1.0
    assert not bool(info["success"])  # nothing happens by standing still
    assert env.unwrapped.instruction.split()[0] in ("put", "push", "pull", "move")


@pytest.mark.parametrize("task", TASKS)
def test_optimal_plan_succeeds_and_replays(sims, task):
    env, runner, state = sims[task]
    for seed in (11, 12):
        rec = record_episode(env, runner, state, _scene(task), "optimal", seed)
        assert rec.success[-1], f"{task} seed {seed}: optimal plan did not succeed"
        assert not rec.success[0]
        T = len(rec.action)
        assert rec.third.shape == (T + 1, 64, 64, 3) and rec.ee_pose.shape == (T + 1, 7) and rec.qpos.shape == (T + 1, 9)
        assert np.abs(rec.action).max() <= 1.0 + 1e-6
        replayed = replay(env, seed, rec.action)  # open loop, pd_ee_delta_pose
        assert replayed[-1], f"{task} seed {seed}: recorded delta-EE actions did not reproduce success"


def test_suboptimal_executions_differ_from_optimal(sims):
    env, runner, state = sims["pick_place"]
    scene = _scene("pick_place")
    opt = record_episode(env, runner, state, scene, "optimal", 21)
    subs = {k: record_episode(env, runner, state, scene, k, 21) for k in ("waypoint_noise", "interpolate", "grasp_disturb")}
    for sub in subs.values():
        assert len(sub.action) > len(opt.action)  # same start state, extra waypoints
        assert np.array_equal(sub.ee_pose[0], opt.ee_pose[0])
    # unrelated waypoints take the TCP far from anywhere the optimal trajectory goes;
    # interpolation and grasp disturbances stay close to it
    def max_dev(rec):
        return np.linalg.norm(rec.ee_pose[:, None, :3] - opt.ee_pose[None, :, :3], axis=-1).min(1).max()

    assert max_dev(subs["waypoint_noise"]) > 0.05
    assert max_dev(subs["interpolate"]) < 0.03
    assert max_dev(subs["grasp_disturb"]) < max_dev(subs["waypoint_noise"])


@pytest.mark.parametrize("task", ["pick_place", "push"])
def test_a_recovery_demonstration_errs_first_and_still_succeeds(sims, task):
    env, runner, state = sims[task]
    opt = record_episode(env, runner, state, _scene(task), "optimal", 31)
    rec = record_episode(env, runner, state, _scene(task), "recover", 31)
    assert rec.success[-1] and not rec.success[0], f"{task}: the recovery demonstration did not succeed"
    assert len(rec.action) > len(opt.action)  # the mistake and the way back are extra steps
    assert np.array_equal(rec.ee_pose[0], opt.ee_pose[0])
    # the demonstration proper starts where the mistake ends: the object has not moved yet, and for
    # pick & place the gripper, closed on nothing, is about to reopen
    assert 0 < rec.demo_from < len(rec.action) and opt.demo_from == 0
    assert np.abs(rec.obj_pose[rec.demo_from, :3] - rec.obj_pose[0, :3]).max() < 0.005
    if task == "pick_place":
        assert rec.action[rec.demo_from - 1, 6] == -1.0 and rec.action[rec.demo_from, 6] == 1.0


def test_make_task_env_observation_format():
    env = make_task_env("push", DEFAULT_SCENE, seed=3)
    obs, info = env.reset(seed=3)
    assert set(obs) == {"third", "wrist", "state"}
    assert obs["third"].dtype == np.uint8 and obs["third"].shape == (64, 64, 3)
    assert obs["state"].shape == (16,)
    obs, reward, terminated, truncated, info = env.step(np.zeros(7, np.float32))
    assert isinstance(info["success"], bool) and isinstance(reward, float)
    assert info["instruction"] == "push the small red cube forward"
    env.close()


def test_stage_run_writes_a_readable_artifact(sims, tmp_path):
    import json

    from pipeline.context import StageContext
    from stages.collect import Config, run
    from stages.collect.contact_sheet import render
    from stages.collect.dataset import Dataset
    from stages.collect.plans import FAILURE_KINDS

    cfg = Config(tasks=("push",), ind_scenes=1, ood_scenes=1, optimal_per_scene=1, ood_optimal_per_scene=1,
                 suboptimal_ratio=1.0, replay_fraction=1.0, episodes_per_shard=3)
    out = tmp_path / "out"
    out.mkdir()
    run(StageContext(stage="collect", config=cfg, inputs={}, out=out, seed=0))
    metrics = json.loads((out / "metrics.json").read_text())
    # per split: one optimal, one suboptimal, one near-miss and one grasp-miss (the world model's negatives)
    assert metrics["episodes"] == metrics["episodes_planned"] == 8
    assert metrics["episodes_by_split"] == {"ind": 4, "ood": 4}
    assert metrics["episodes_by_kind"]["near_miss"] == metrics["episodes_by_kind"]["grasp_miss"] == 2
    assert metrics["replay_success_rate"] == 1.0 and metrics["replayed"] == 2
    ds = Dataset(out)
    assert {m.split for m in ds.episodes} == {"ind", "ood"}
    assert all(m.success != (m.kind in FAILURE_KINDS) for m in ds.episodes)  # demonstrations succeed, failures fail
    for m in ds.episodes:  # a grasp-miss never moves the object: the fingers close / slide beside it
        if m.kind == "grasp_miss":
            obj = ds.load_states(m.episode_id)["obj_pose"]
            assert np.abs(obj[-1, :3] - obj[0, :3]).max() < 0.005, m.episode_id
    scenes = json.loads((out / "scenes.json").read_text())["scenes"]
    by_id = {s["scene_id"]: s for s in scenes}
    assert all(by_id[m.scene_id]["split"] == m.split for m in ds.episodes)
    ep = ds.load(next(m for m in ds.episodes if m.kind == "optimal").episode_id)
    assert ep.third.shape[1:] == (64, 64, 3) and ep.success[-1]
    sheet = render(out, n_frames=4, scale=1)
    assert sheet.width == 4 * 64


def test_asset_download_prompt_is_refused():
    from mani_skill.utils import download_asset

    from stages.collect.envs import AssetDownloadRefused

    with pytest.raises(AssetDownloadRefused, match="never downloads"):
        download_asset.prompt_yes_no("download YCB?")


@pytest.mark.parametrize("task", TASKS)
def test_composed_actions_repeated_reproduce_success(sims, task):
    """Frame skip is sound: the world model's composed actions, each repeated k times, still succeed."""
    from stages.common.frame_skip import compose_actions

    env, runner, state = sims[task]
    rec = record_episode(env, runner, state, _scene(task), "optimal", 11)
    k = 4
    repeated = np.repeat(compose_actions(rec.action, k), k, axis=0)  # (k * ceil(T/k), 7)
    assert len(repeated) >= len(rec.action)
    assert replay(env, 11, repeated).any(), f"{task}: composed actions repeated {k}x did not reach success"
