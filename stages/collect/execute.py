"""Run a waypoint plan in the simulator and record it as delta-EE actions.

MPLib (through ManiSkill's ``PandaArmMotionPlanningSolver``) plans each Move as a joint-space
path at the control rate. The env runs the ``pd_ee_delta_pose`` controller: every planned joint
configuration is turned, through forward kinematics, into a target TCP pose, and the recorded
action is the normalized delta from the *current* TCP pose to it (``actions.delta_ee_action``).
So the recorded action is exactly the command the controller executed, and replaying the actions
open-loop from the same initial state reproduces the episode (``replay``).
"""
from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass

from stages.common.vulkan import ensure_vulkan

ensure_vulkan()  # before sapien is imported

import numpy as np
import sapien

from mani_skill.examples.motionplanning.base_motionplanner.utils import compute_grasp_info_by_obb, get_actor_obb
from mani_skill.examples.motionplanning.panda.motionplanner import PandaArmMotionPlanningSolver

from stages.collect import envs as task_envs
from stages.collect.actions import GRIPPER_OPEN, controller_scales, delta_ee_action
from stages.collect.plans import Grip, Layout, Move

REFINE_STEPS = 2  # extra steps at the end of each motion so the arm settles on the waypoint


class PlanFailure(RuntimeError):
    """MPLib found no path to a waypoint, or the episode ran past its step limit."""


@dataclass
class Recording:
    """One episode's arrays (see ``dataset.Episode`` for shapes)."""

    third: np.ndarray
    wrist: np.ndarray
    action: np.ndarray
    ee_pose: np.ndarray
    qpos: np.ndarray
    reward: np.ndarray
    success: np.ndarray
    obj_pose: np.ndarray
    demo_from: int = 0  # actions before this belong to a deliberate mistake (plan steps labelled "err"): never imitated


def layout_from_env(env) -> Layout:
    """The plan inputs read from the env's current (just reset) state."""
    u = env.unwrapped
    obj_p = u.obj.pose.sp.p
    tcp = u.agent.tcp.pose.sp
    obb = get_actor_obb(u.obj)
    closing_hint = u.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy()
    info = compute_grasp_info_by_obb(obb, approaching=np.array([0, 0, -1]), target_closing=closing_hint, depth=0.025)
    grasp = u.agent.build_grasp_pose(np.array([0, 0, -1.0]), info["closing"], obj_p)
    common = dict(task=u.task, obj_p=tuple(obj_p), obj_half=u.obj_half, grasp_q=tuple(grasp.q), down_q=tuple(tcp.q))
    if u.task == "pick_place":
        c = u.container.pose.sp.p
        return Layout(**common, target_p=tuple(c), place_z=u.container_top + u.obj_rest_z + 0.012)
    if u.task == "move_to_aim":
        a = u.carpet.pose.sp.p
        return Layout(**common, target_p=tuple(a), place_z=u.obj_rest_z + 0.01)
    goal = u.goal_xy[0].numpy()
    return Layout(**common, target_p=(goal[0], goal[1], obj_p[2]), direction=u.direction, slide_distance=task_envs.MOVE_DISTANCE)


class PlanRunner:
    """Executes plans in one env (``pd_ee_delta_pose``, RGB obs) and records the episode."""

    def __init__(self, env, max_steps: int):
        self.env, self.max_steps = env, max_steps
        self.pos_scale, self.rot_scale = controller_scales(env)
        self._solver = None
        self._solver_robot = None

    # -- kinematics -------------------------------------------------------------------------
    @property
    def _arm(self):
        return self.env.unwrapped.agent.controller.controllers["arm"]

    def _tcp_at_base(self) -> np.ndarray:
        return self._arm.ee_pose_at_base.raw_pose[0].cpu().numpy().astype(np.float64)

    def _fk_at_base(self, arm_q: np.ndarray) -> np.ndarray:
        """TCP pose (robot-base frame) for the 7 arm joint angles ``arm_q``."""
        kin = self._arm.kinematics
        full = self.env.unwrapped.agent.robot.get_qpos()[0].cpu().numpy().astype(np.float64)
        full[:7] = arm_q
        kin.pmodel.compute_forward_kinematics(full[kin.pmodel_active_joint_indices.cpu().numpy()])
        pose = kin.pmodel.get_link_pose(kin.end_link_idx)
        return np.concatenate([pose.p, pose.q])

    def _solver_for_env(self) -> PandaArmMotionPlanningSolver:
        robot = self.env.unwrapped.agent.robot
        if self._solver is None or self._solver_robot is not robot:  # rebuilt after a reconfigure
            self._solver = PandaArmMotionPlanningSolver(
                self.env, debug=False, vis=False, base_pose=robot.pose, visualize_target_grasp_pose=False, print_env_info=False
            )
            self._solver_robot = robot
        return self._solver

    def _plan(self, pose: tuple) -> np.ndarray:
        """Joint path (N, 7) to a world-frame TCP pose: screw motion, RRTConnect as fallback."""
        solver = self._solver_for_env()
        target = sapien.Pose(p=list(pose[:3]), q=list(pose[3:]))
        with contextlib.redirect_stdout(io.StringIO()):  # the solver prints planner statuses
            res = solver.move_to_pose_with_screw(target, dry_run=True)
            if res == -1:
                res = solver.move_to_pose_with_RRTConnect(target, dry_run=True)
        if res == -1:
            raise PlanFailure(f"no path to waypoint {np.round(pose[:3], 3).tolist()}")
        return np.asarray(res["position"])

    # -- recording --------------------------------------------------------------------------
    def run(self, plan: list, obs, info) -> Recording:
        """Execute ``plan`` from the env's current state (``obs``, ``info`` from its reset)."""
        frames: dict[str, list] = {k: [] for k in ("third", "wrist", "ee_pose", "qpos", "action", "reward", "success", "obj_pose")}
        self._record_obs(frames, obs, info)
        gripper = GRIPPER_OPEN
        hold = self._tcp_at_base()
        demo_from, in_mistake = 0, False
        for step in plan:
            if step.label == "err":
                in_mistake = True
            elif in_mistake:  # the first step after a mistake: the demonstration proper starts here
                demo_from, in_mistake = len(frames["action"]), False
            if isinstance(step, Grip):
                gripper = step.value
                for _ in range(step.steps):
                    obs, info = self._step(frames, delta_ee_action(self._tcp_at_base(), hold, gripper, self.pos_scale, self.rot_scale))
            elif isinstance(step, Move):
                path = self._plan(step.pose)
                targets = [self._fk_at_base(q) for q in path[1:]] or [self._fk_at_base(path[-1])]
                targets += [targets[-1]] * REFINE_STEPS
                for tgt in targets:
                    obs, info = self._step(frames, delta_ee_action(self._tcp_at_base(), tgt, gripper, self.pos_scale, self.rot_scale))
                hold = targets[-1]
            else:
                raise TypeError(f"unknown plan step {step!r}")
        return Recording(
            third=np.stack(frames["third"]), wrist=np.stack(frames["wrist"]),
            action=np.stack(frames["action"]).astype(np.float32), ee_pose=np.stack(frames["ee_pose"]).astype(np.float32),
            qpos=np.stack(frames["qpos"]).astype(np.float32), reward=np.asarray(frames["reward"], np.float32),
            success=np.asarray(frames["success"], bool), obj_pose=np.stack(frames["obj_pose"]).astype(np.float32),
            demo_from=demo_from,
        )

    def _step(self, frames: dict, action: np.ndarray):
        if len(frames["action"]) >= self.max_steps:
            raise PlanFailure(f"episode exceeded max_steps={self.max_steps}")
        obs, reward, _, _, info = self.env.step(action[None])
        frames["action"].append(action)
        frames["reward"].append(float(reward.reshape(-1)[0]))
        self._record_obs(frames, obs, info)
        return obs, info

    def _record_obs(self, frames: dict, obs, info) -> None:
        sd = obs["sensor_data"]
        frames["third"].append(sd["third"]["rgb"][0].cpu().numpy().astype(np.uint8))
        frames["wrist"].append(sd["wrist"]["rgb"][0].cpu().numpy().astype(np.uint8))
        frames["ee_pose"].append(obs["extra"]["tcp_pose"][0].cpu().numpy())
        frames["qpos"].append(obs["agent"]["qpos"][0].cpu().numpy())
        frames["success"].append(bool(info["success"].reshape(-1)[0]))
        frames["obj_pose"].append(self.env.unwrapped.obj.pose.raw_pose[0].cpu().numpy())  # ground truth for probes only


def replay(env, seed: int, actions: np.ndarray, options: dict | None = None) -> np.ndarray:
    """Open-loop replay of ``actions`` (T, 7) from ``reset(seed)``; returns success (T+1,) bool."""
    _, info = env.reset(seed=seed, options=options)
    success = [bool(info["success"].reshape(-1)[0])]
    for a in actions:
        _, _, _, _, info = env.step(np.asarray(a, np.float32)[None])
        success.append(bool(info["success"].reshape(-1)[0]))
    return np.asarray(success)
