"""The planner takes over from an arbitrary state: the rest of a task planned from where the object
and the gripper are now, not from a reset.

Used where demonstrations must continue from a policy's own states (the sft stage's DAgger rounds,
``stages.sft.dagger``) and by ``scripts/takeover_probe.py``, which measured how often the planner
finishes from where the SFT policy stopped (docs/sft.md, "DAgger with the planner as the expert").
"""
from __future__ import annotations

import dataclasses

from stages.collect.plans import Grip, Layout, optimal_plan

PLACING = ("pick_place", "move_to_aim")  # tasks that grasp, carry and release; push and pull slide the object


def takeover_plan(lay: Layout, grasped: bool, remaining: float) -> list:
    """The rest of the task from the current state. ``lay``: read from the current state
    (``stages.collect.execute.layout_from_env``); ``grasped``: the gripper holds the object;
    ``remaining``: for push / pull, how far (m, along the slide direction) the object still has to go.

    Placing tasks: holding the object, keep the gripper closed and lift, carry, place, release,
    retreat (the optimal plan after its grasp); otherwise open the gripper and plan the whole task from
    the object's current place. Push / pull: the optimal plan with the slide shortened to what remains.
    """
    if lay.task in PLACING:
        plan = optimal_plan(lay)
        if grasped:  # the runner starts with the gripper open: command it closed before the first move
            return [Grip(-1.0, 1), *plan[3:]]  # plan[3:]: after pre, grasp and the close
        return [Grip(1.0, 6), *plan]
    return optimal_plan(dataclasses.replace(lay, slide_distance=max(float(remaining), 0.0)))


def current_state(env) -> tuple[Layout, bool, float]:
    """(layout, grasped, remaining slide in m) of a ManiSkill task env's current state."""
    from stages.collect.execute import layout_from_env

    u = env.unwrapped
    lay = layout_from_env(env)
    grasped = bool(u.agent.is_grasping(u.obj).reshape(-1)[0])
    remaining = 0.0
    if lay.task not in PLACING:
        goal_x = float(u.goal_xy[0, 0])
        remaining = lay.direction * (goal_x - float(u.obj.pose.p[0, 0]))
    return lay, grasped, remaining


@dataclasses.dataclass
class Takeover:
    """The planner's continuation from a state: ``recording`` (``stages.collect.execute.Recording``,
    first frame = that state) or None with ``error`` saying why no plan completed."""

    grasped: bool
    remaining: float
    recording: object | None = None
    error: str = ""

    @property
    def success(self) -> bool:
        return self.recording is not None and bool(self.recording.success.any())


def take_over(env, max_steps: int) -> Takeover:
    """Run the planner from ``env``'s current state (a ManiSkill task env, not wrapped) for at most
    ``max_steps`` control steps; no path to a waypoint or a longer plan: no recording."""
    from stages.collect.execute import PlanFailure, PlanRunner

    lay, grasped, remaining = current_state(env)
    base = env.unwrapped
    info = base.get_info()
    obs = base.get_obs(info, unflattened=True)
    try:
        rec = PlanRunner(env, max_steps).run(takeover_plan(lay, grasped, remaining), obs, info)
    except PlanFailure as err:
        return Takeover(grasped, remaining, error=str(err))
    return Takeover(grasped, remaining, rec)
