"""The four tabletop tasks (paper §4.1) as registered ManiSkill envs, with scenes from primitives.

All four share one scene layout: a colored table (box, top at z=0), a Panda at x=-0.615 facing +x,
one primitive object, one container (plate or bowl; a distractor outside pick & place) and, for
move to aim, a flat target carpet. "Forward" is +x (away from the robot).

**Task Description:**
- ``RSPickPlace-v1``: put the object in the container.
- ``RSPush-v1``: push the object forward (+x) by ``MOVE_DISTANCE``.
- ``RSPull-v1``: pull the object back (-x) by ``MOVE_DISTANCE``.
- ``RSMoveToAim-v1``: move the object onto the target carpet.

**Randomizations:** object xy (and yaw for cubes: up to 45 degrees, 15 for push / pull), container xy, carpet xy, robot joints
(N(0, 0.02) noise); rejection-sampled so that object, container and carpet do not overlap and the
container is off the push/pull path. The scene (object x container x table) comes from the
``scene`` kwarg (a catalog ``Scene.to_dict()``), or ``options["scene"]`` with ``reconfigure=True``.

**Success Conditions:** see each class's ``evaluate``; all are position checks on the object.
"""
from __future__ import annotations

from typing import Any

from stages.collect.tasks import TASKS
from stages.common.vulkan import ensure_vulkan

ensure_vulkan()  # before sapien is imported

import numpy as np
import sapien
import torch

from mani_skill.agents.robots import Panda
from mani_skill.utils import download_asset
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.pose import Pose

from stages.collect import ee_pose


class AssetDownloadRefused(RuntimeError):
    """ManiSkill asked to download assets; this project only uses what ships in the wheel."""


def _refuse_asset_download(message: str) -> bool:
    raise AssetDownloadRefused(
        f"ManiSkill asked to download assets ({message.strip()!r}); this project never downloads "
        "assets: its scenes are built from primitives and the Panda that ships with mani-skill"
    )


# ManiSkill's registration and agent loading call download_asset.prompt_yes_no, which would block
# on stdin (or raise EOFError in a worker): replace it with a clear error, once, at import.
download_asset.prompt_yes_no = _refuse_asset_download

ROBOT_BASE = (-0.615, 0.0, 0.0)
REST_QPOS = np.array([0.0, np.pi / 8, 0, -np.pi * 5 / 8, 0, np.pi * 3 / 4, np.pi / 4, 0.04, 0.04])
MOVE_DISTANCE = 0.10  # push / pull distance (m)
GOAL_TOL = 0.03  # push / pull success radius around the goal point (m)
CONTAINER_RADIUS = 0.075
CARPET_HALF = 0.05
CONTAINER_COLOR = (0.92, 0.92, 0.9)
CARPET_COLOR = (0.55, 0.2, 0.75)
THIRD_CAMERA_EYE = (0.3, 0.0, 0.42)
THIRD_CAMERA_TARGET = (-0.08, 0.0, 0.0)
THIRD_CAMERA_FOV = 0.8  # rad; in front of and above the table, so a 4.4 cm object spans ~5-7 px at 64x64
WRIST_CAMERA_FOV = 1.4  # rad

DEFAULT_SCENE = {
    "scene_id": "small-red-cube__bowl__wood",
    "object": {"name": "small red cube", "shape": "cube", "half_size": 0.022, "color": [0.85, 0.1, 0.1]},
    "container": "bowl",
    "table": {"name": "wood", "color": [0.55, 0.4, 0.25]},
    "split": "ind",
    "ood_reason": None,
}


def _material(rgb) -> sapien.render.RenderMaterial:
    return sapien.render.RenderMaterial(base_color=[*map(float, rgb), 1.0])


def object_rest_height(shape: str, half: float) -> float:
    """z of the object's centre when it rests on the table."""
    return capsule_radius(half) if shape == "capsule" else half


def capsule_radius(half: float) -> float:
    return 0.6 * half


class RSTabletopEnv(BaseEnv):
    """Shared scene building, cameras, robot reset and reward plumbing for the four tasks."""

    SUPPORTED_ROBOTS = ["panda"]
    agent: Panda
    task: str = ""
    instruction_template: str = ""

    def __init__(self, *args, scene: dict | None = None, image_size: int = 64, robot_init_qpos_noise: float = 0.02, **kwargs):
        self.scene_spec = dict(scene or DEFAULT_SCENE)
        self.image_size = int(image_size)
        self.robot_init_qpos_noise = robot_init_qpos_noise
        kwargs.setdefault("robot_uids", "panda")
        super().__init__(*args, **kwargs)

    # ---- instruction --------------------------------------------------------------------------
    @property
    def instruction(self) -> str:
        """The task instruction for the current scene, e.g. "put the small red cube in the bowl"."""
        return self.instruction_template.format(object=self.scene_spec["object"]["name"], container=self.scene_spec["container"])

    # ---- cameras ------------------------------------------------------------------------------
    @property
    def _default_sensor_configs(self):
        s = self.image_size
        third = sapien_utils.look_at(eye=THIRD_CAMERA_EYE, target=THIRD_CAMERA_TARGET)
        # Hand frame: +z points from the palm to the fingertips. The camera (which looks along its
        # own +x) sits 7 cm off the palm and looks along +z, tilted so the fingertips are in view.
        wrist = sapien.Pose(p=[0.07, 0.0, 0.0], q=_euler_y(-np.pi / 2 - 0.35))
        return [
            CameraConfig("third", third, s, s, THIRD_CAMERA_FOV, 0.01, 10),
            CameraConfig("wrist", wrist, s, s, WRIST_CAMERA_FOV, 0.01, 10, mount=self.agent.robot.links_map["panda_hand"]),
        ]

    @property
    def _default_human_render_camera_configs(self):
        pose = sapien_utils.look_at(eye=THIRD_CAMERA_EYE, target=THIRD_CAMERA_TARGET)
        return CameraConfig("render_camera", pose, 256, 256, THIRD_CAMERA_FOV, 0.01, 10)

    # ---- scene --------------------------------------------------------------------------------
    def _load_agent(self, options: dict):
        super()._load_agent(options, sapien.Pose(p=list(ROBOT_BASE)))
        ee_pose.speed_up(self.agent)  # the same poses bit for bit, without torch's per-op cost (ee_pose.py)

    def _load_scene(self, options: dict):
        if options.get("scene") is not None:
            self.scene_spec = dict(options["scene"])
        spec = self.scene_spec
        table = self.scene.create_actor_builder()
        table.add_box_collision(sapien.Pose(p=[0, 0, -0.02]), half_size=[0.7, 0.8, 0.02])
        table.add_box_visual(sapien.Pose(p=[0, 0, -0.02]), half_size=[0.7, 0.8, 0.02], material=_material(spec["table"]["color"]))
        table.initial_pose = sapien.Pose()
        self.table = table.build_static(name="table")
        floor = self.scene.create_actor_builder()
        floor.add_box_visual(sapien.Pose(p=[0, 0, -0.9]), half_size=[3, 3, 0.01], material=_material((0.35, 0.35, 0.38)))
        floor.initial_pose = sapien.Pose()
        self.floor = floor.build_static(name="floor")

        obj = spec["object"]
        self.obj_shape, self.obj_half = obj["shape"], float(obj["half_size"])
        self.obj_rest_z = object_rest_height(self.obj_shape, self.obj_half)
        self.obj = _build_object(self.scene, obj["shape"], self.obj_half, obj["color"])
        self.container_kind = spec["container"]
        self.container = _build_container(self.scene, spec["container"])
        self.container_top = 0.006 if spec["container"] == "plate" else 0.005
        if self.task == "move_to_aim":
            carpet = self.scene.create_actor_builder()
            carpet.add_box_visual(half_size=[CARPET_HALF, CARPET_HALF, 0.001], material=_material(CARPET_COLOR))
            carpet.initial_pose = sapien.Pose(p=[0, 0, 0.001])
            self.carpet = carpet.build_kinematic(name="carpet")

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        rng = self._episode_rng
        qpos = REST_QPOS + rng.normal(0, self.robot_init_qpos_noise, len(REST_QPOS))
        qpos[-2:] = 0.04
        self.agent.reset(qpos[None])
        self.agent.robot.set_pose(sapien.Pose(p=list(ROBOT_BASE)))
        layout = self._sample_layout(rng)
        yaw = rng.uniform(-self.max_cube_yaw, self.max_cube_yaw) if self.obj_shape == "cube" else 0.0
        self.obj.set_pose(Pose.create_from_pq(torch.tensor([[*layout["object"], self.obj_rest_z]]), torch.tensor([_yaw_quat(yaw)])))
        self.container.set_pose(Pose.create_from_pq(torch.tensor([[*layout["container"], 0.0]])))
        if self.task == "move_to_aim":
            self.carpet.set_pose(Pose.create_from_pq(torch.tensor([[*layout["carpet"], 0.001]])))
        self.obj_init_xy = torch.tensor([layout["object"]], dtype=torch.float32)  # (1, 2)

    def _sample_layout(self, rng) -> dict:
        """Object / container / carpet xy positions that do not overlap (rejection sampling)."""
        x_lo, x_hi = self.object_x_range
        for _ in range(1000):
            o = np.array([rng.uniform(x_lo, x_hi), rng.uniform(-0.12, 0.12)])
            c = np.array([rng.uniform(-0.1, 0.12), rng.uniform(-0.2, 0.2)])
            if np.linalg.norm(o - c) < 0.17:
                continue
            if self.task in ("push", "pull") and abs(o[1] - c[1]) < 0.15:
                continue
            layout = {"object": o.tolist(), "container": c.tolist()}
            if self.task == "move_to_aim":
                a = np.array([rng.uniform(-0.1, 0.12), rng.uniform(-0.18, 0.18)])
                if np.linalg.norm(a - o) < 0.13 or np.linalg.norm(a - c) < 0.16:
                    continue
                layout["carpet"] = a.tolist()
            return layout
        raise RuntimeError("could not sample a non-overlapping layout in 1000 tries")

    object_x_range = (-0.08, 0.08)
    max_cube_yaw = np.pi / 4

    # ---- shared reward pieces -----------------------------------------------------------------
    def _reach_reward(self, target_p: torch.Tensor) -> torch.Tensor:
        return 1 - torch.tanh(5 * torch.linalg.norm(target_p - self.agent.tcp_pose.p, axis=1))

    def _obj_resting(self) -> torch.Tensor:
        return self.obj.pose.p[:, 2] < self.obj_rest_z + self.container_top + 0.015

    def _get_obs_extra(self, info: dict):
        return dict(tcp_pose=self.agent.tcp_pose.raw_pose)

    def compute_normalized_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        return self.compute_dense_reward(obs=obs, action=action, info=info) / 5


class _PlaceTask(RSTabletopEnv):
    """Pick the object and set it down at a target (container or carpet); shared by two tasks."""

    def _target_xy(self) -> torch.Tensor:
        raise NotImplementedError

    def _target_radius(self) -> float:
        raise NotImplementedError

    def evaluate(self):
        xy_dist = torch.linalg.norm(self.obj.pose.p[:, :2] - self._target_xy(), axis=1)
        is_grasped = self.agent.is_grasping(self.obj)
        is_obj_placed = (xy_dist < self._target_radius()) & self._obj_resting()
        return {"success": is_obj_placed & ~is_grasped, "is_obj_placed": is_obj_placed, "is_grasped": is_grasped}

    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        reward = self._reach_reward(self.obj.pose.p)
        grasped = info["is_grasped"].float()
        xy_dist = torch.linalg.norm(self.obj.pose.p[:, :2] - self._target_xy(), axis=1)
        place = 1 - torch.tanh(5 * xy_dist)
        reward = reward + grasped + 2 * place * torch.maximum(grasped, info["is_obj_placed"].float())
        reward[info["success"]] = 5
        return reward


@register_env("RSPickPlace-v1", max_episode_steps=400)
class PickPlaceEnv(_PlaceTask):
    """Put the object in the container (plate or bowl). Success: object centre within the
    container's inner radius, resting low, and released."""

    task = "pick_place"
    instruction_template = "put the {object} in the {container}"

    def _target_xy(self):
        return self.container.pose.p[:, :2]

    def _target_radius(self):
        return CONTAINER_RADIUS - 0.015


@register_env("RSMoveToAim-v1", max_episode_steps=400)
class MoveToAimEnv(_PlaceTask):
    """Move the object onto the purple target carpet. Success: object centre over the carpet,
    resting on the table, and released."""

    task = "move_to_aim"
    instruction_template = "move the {object} onto the purple carpet"

    def _target_xy(self):
        return self.carpet.pose.p[:, :2]

    def _target_radius(self):
        return CARPET_HALF

    def _obj_resting(self):
        return self.obj.pose.p[:, 2] < self.obj_rest_z + 0.015


class _SlideTask(RSTabletopEnv):
    """Slide the object along x by ``direction * MOVE_DISTANCE`` with a closed gripper."""

    direction = 1.0
    max_cube_yaw = np.pi / 12  # a cube slid by a narrow contact at 45 degrees would drift sideways

    @property
    def goal_xy(self) -> torch.Tensor:  # (1, 2)
        return self.obj_init_xy + torch.tensor([[self.direction * MOVE_DISTANCE, 0.0]])

    def evaluate(self):
        dist = torch.linalg.norm(self.obj.pose.p[:, :2] - self.goal_xy, axis=1)
        return {"success": dist < GOAL_TOL, "goal_dist": dist}

    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        behind = self.obj.pose.p.clone()
        behind[:, 0] -= self.direction * (self.obj_half + 0.02)
        reward = self._reach_reward(behind)
        # the goal term pays the progress made, 0 while the object has not moved towards its goal: a
        # distance-based term paid ~1.6 (of 5) for the untouched object and PPO learned to hover behind it
        progress = torch.clamp(1 - info["goal_dist"] / MOVE_DISTANCE, 0.0, 1.0)
        reward = reward + 3 * progress
        reward[info["success"]] = 5
        return reward


@register_env("RSPush-v1", max_episode_steps=400)
class PushEnv(_SlideTask):
    """Push the object forward (+x, away from the robot) by 10 cm. Success: object centre within
    3 cm of its start + (0.10, 0)."""

    task = "push"
    instruction_template = "push the {object} forward"
    direction = 1.0
    object_x_range = (-0.1, 0.0)


@register_env("RSPull-v1", max_episode_steps=400)
class PullEnv(_SlideTask):
    """Pull the object back (-x, toward the robot) by 10 cm. Success: object centre within 3 cm
    of its start - (0.10, 0)."""

    task = "pull"
    instruction_template = "pull the {object} back"
    direction = -1.0
    object_x_range = (0.0, 0.1)


TASK_ENV_IDS = {"pick_place": "RSPickPlace-v1", "push": "RSPush-v1", "pull": "RSPull-v1", "move_to_aim": "RSMoveToAim-v1"}
assert tuple(TASK_ENV_IDS) == TASKS, "every task of stages.collect.tasks has one env, in order"


# ---- primitive builders ---------------------------------------------------------------------------
def _euler_y(angle: float) -> list[float]:
    return [float(np.cos(angle / 2)), 0.0, float(np.sin(angle / 2)), 0.0]


def _yaw_quat(yaw: float) -> list[float]:
    return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


_Z_UP = sapien.Pose(q=_euler_y(np.pi / 2))  # SAPIEN cylinders/capsules lie along local x
_ALONG_Y = sapien.Pose(q=_yaw_quat(np.pi / 2))


def _build_object(scene, shape: str, half: float, color) -> Any:
    b = scene.create_actor_builder()
    mat = _material(color)
    if shape == "cube":
        b.add_box_collision(half_size=[half] * 3)
        b.add_box_visual(half_size=[half] * 3, material=mat)
    elif shape == "cylinder":
        b.add_cylinder_collision(_Z_UP, radius=half, half_length=half)
        b.add_cylinder_visual(_Z_UP, radius=half, half_length=half, material=mat)
    elif shape == "sphere":
        b.add_sphere_collision(radius=half)
        b.add_sphere_visual(radius=half, material=mat)
    elif shape == "capsule":
        r = capsule_radius(half)
        b.add_capsule_collision(_ALONG_Y, radius=r, half_length=half - r)
        b.add_capsule_visual(_ALONG_Y, radius=r, half_length=half - r, material=mat)
    else:
        raise ValueError(f"unknown object shape {shape!r}")
    b.initial_pose = sapien.Pose(p=[0, 0, 0.1])
    actor = b.build(name="object")
    # Spheres and capsules would roll away on any touch; damping keeps pushes and placements local.
    for body in actor._bodies:
        body.set_angular_damping(3.0)
        body.set_linear_damping(0.5)
    return actor


def _build_container(scene, kind: str) -> Any:
    b = scene.create_actor_builder()
    mat = _material(CONTAINER_COLOR)
    if kind == "plate":
        b.add_cylinder_collision(sapien.Pose(p=[0, 0, 0.003], q=_Z_UP.q), radius=CONTAINER_RADIUS, half_length=0.003)
        b.add_cylinder_visual(sapien.Pose(p=[0, 0, 0.003], q=_Z_UP.q), radius=CONTAINER_RADIUS, half_length=0.003, material=mat)
    elif kind == "bowl":
        b.add_cylinder_collision(sapien.Pose(p=[0, 0, 0.0025], q=_Z_UP.q), radius=CONTAINER_RADIUS, half_length=0.0025)
        b.add_cylinder_visual(sapien.Pose(p=[0, 0, 0.0025], q=_Z_UP.q), radius=CONTAINER_RADIUS, half_length=0.0025, material=mat)
        n = 16
        seg = CONTAINER_RADIUS * np.tan(np.pi / n) * 1.05
        for i in range(n):
            a = 2 * np.pi * i / n
            pose = sapien.Pose(p=[CONTAINER_RADIUS * np.cos(a), CONTAINER_RADIUS * np.sin(a), 0.018], q=_yaw_quat(a))
            b.add_box_collision(pose, half_size=[0.003, seg, 0.018])
            b.add_box_visual(pose, half_size=[0.003, seg, 0.018], material=mat)
    else:
        raise ValueError(f"unknown container {kind!r}; expected 'plate' or 'bowl'")
    b.initial_pose = sapien.Pose(p=[0.3, 0.3, 0])
    return b.build_kinematic(name="container")
