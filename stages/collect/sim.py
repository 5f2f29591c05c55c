"""Build a task env in the simulator: what collect records with, and what evaluate / the
"RL in ManiSkill" baseline step.

``make_task_env(task, scene)`` returns a gymnasium env (single, CPU physics and rendering) whose
observation is a dict of numpy arrays::

    obs["third"]: (H, W, 3) uint8   third-view RGB (H = W = image_size)
    obs["wrist"]: (H, W, 3) uint8   wrist (hand) camera RGB
    obs["state"]: (16,) float32     TCP pose (xyz + quaternion wxyz, world frame; the robot
                                    base sits at x=-0.615) then the 9 joint positions

``step(action)`` takes a (7,) float array; under the default ``pd_ee_delta_pose`` controller that
is the normalized delta end-effector pose (see ``stages.collect.actions``). ``reward`` is the
task's normalized dense rule reward (in [0, 1]); ``info["success"]`` is the task's success check
(a Python bool), ``info["instruction"]`` the instruction text.
"""
from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from stages.common.vulkan import ensure_vulkan, raise_if_no_device
from stages.collect.catalog import Scene, read_scenes_json
from stages.collect.tasks import TASKS


def _import_envs():
    """Register the task envs (imports sapien, so Vulkan must be set up first)."""
    ensure_vulkan()
    from stages.collect import envs  # noqa: F401  (registers RS*-v1)

    return envs


def default_catalog() -> dict[str, Scene]:
    """scene_id -> Scene for the catalog of the collect stage's default config."""
    from stages.collect import Config, scene_catalog

    return {s.scene_id: s for s in scene_catalog(Config())}


def get_scene(scene_id: str, catalog: str | Path | None = None) -> Scene:
    """The catalog scene ``scene_id``; ``catalog`` is a collect artifact dir or its scenes.json
    (default: the catalog of the default collect config)."""
    if catalog is None:
        scenes = default_catalog()
    else:
        path = Path(catalog)
        scenes = read_scenes_json(path / "scenes.json" if path.is_dir() else path)
    try:
        return scenes[scene_id]
    except KeyError:
        raise KeyError(f"scene {scene_id!r} is not in the catalog ({catalog or 'default config'}); e.g. {sorted(scenes)[:3]}") from None


class TaskObsWrapper(gym.Wrapper):
    """Unbatches a single ManiSkill env to numpy: obs {third, wrist, state}, float reward, bool success."""

    def __init__(self, env: gym.Env, image_size: int):
        super().__init__(env)
        s = image_size
        self.observation_space = gym.spaces.Dict(
            {
                "third": gym.spaces.Box(0, 255, (s, s, 3), np.uint8),
                "wrist": gym.spaces.Box(0, 255, (s, s, 3), np.uint8),
                "state": gym.spaces.Box(-np.inf, np.inf, (16,), np.float32),
            }
        )
        low, high = env.action_space.low, env.action_space.high
        self.action_space = gym.spaces.Box(low.reshape(-1), high.reshape(-1), dtype=np.float32)

    @property
    def instruction(self) -> str:
        return self.env.unwrapped.instruction

    def _obs(self, obs) -> dict:
        sd = obs["sensor_data"]
        state = np.concatenate([obs["extra"]["tcp_pose"][0].cpu().numpy(), obs["agent"]["qpos"][0].cpu().numpy()])
        return {
            "third": sd["third"]["rgb"][0].cpu().numpy().astype(np.uint8),
            "wrist": sd["wrist"]["rgb"][0].cpu().numpy().astype(np.uint8),
            "state": state.astype(np.float32),
        }

    def _info(self, info) -> dict:
        out = {k: (bool(v.reshape(-1)[0]) if v.dtype == torch.bool else float(v.reshape(-1)[0]))
               for k, v in info.items() if hasattr(v, "dtype") and v.numel() == 1}
        out["success"] = bool(info["success"].reshape(-1)[0])
        out["instruction"] = self.instruction
        return out

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._obs(obs), self._info(info)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(np.asarray(action, dtype=np.float32)[None])
        return (self._obs(obs), float(reward.reshape(-1)[0]), bool(terminated.reshape(-1)[0]),
                bool(truncated.reshape(-1)[0]), self._info(info))


def make_raw_env(task: str, scene: Scene | dict, *, image_size: int = 64, robot_mesh: str = "lowpoly",
                 control_mode: str = "pd_ee_delta_pose", obs_mode: str = "rgb", reward_mode: str = "normalized_dense", **kw):
    """The ManiSkill env (batched torch API, ``num_envs=1``) of ``task`` in ``scene``."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; expected one of {TASKS}")
    envs = _import_envs()
    from stages.collect.robot_mesh import use_robot_mesh

    use_robot_mesh(robot_mesh)
    scene_dict = scene.to_dict() if isinstance(scene, Scene) else dict(scene)
    json.dumps(scene_dict)  # register_env kwargs must be plain data
    try:
        return gym.make(
            envs.TASK_ENV_IDS[task], num_envs=1, obs_mode=obs_mode, control_mode=control_mode, reward_mode=reward_mode,
            sim_backend="physx_cpu", render_backend="cpu", scene=scene_dict, image_size=image_size, **kw,
        )
    except RuntimeError as err:
        raise_if_no_device(err)
        raise


def make_task_env(task: str, scene: Scene | dict | str, *, image_size: int = 64, robot_mesh: str = "lowpoly",
                  control_mode: str = "pd_ee_delta_pose", seed: int = 0, **kw) -> gym.Env:
    """A gymnasium env of ``task`` in ``scene`` (a Scene, its dict, or a scene id of the default
    catalog) with the numpy observation described in this module's docstring.

    :param task: one of ``TASKS``.
    :param image_size: side of both square camera images.
    :param robot_mesh: ``lowpoly`` (fast software rendering) or ``stock``.
    :param control_mode: ManiSkill controller; the dataset's actions are ``pd_ee_delta_pose``.
    :param seed: seeds the first reset (initial object placement and robot joint noise).
    :param kw: passed to ``gym.make`` (e.g. ``max_episode_steps``).
    """
    if isinstance(scene, str):
        scene = get_scene(scene)
    env = TaskObsWrapper(make_raw_env(task, scene, image_size=image_size, robot_mesh=robot_mesh, control_mode=control_mode, **kw), image_size)
    env.reset(seed=seed)
    return env
