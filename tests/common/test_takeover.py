"""The planner's takeover: the rest of the task from the state where a policy stopped (stages.common.takeover)."""
from __future__ import annotations

from stages.collect.plans import Grip, Layout, Move, optimal_plan
from stages.common.takeover import takeover_plan

Q = (1.0, 0.0, 0.0, 0.0)


def _lay(task, **kw):
    return Layout(task=task, obj_p=(0.05, 0.02, 0.02), obj_half=0.02, grasp_q=Q, down_q=Q, target_p=(-0.1, 0.1, 0.02),
                  place_z=0.06, **kw)


def test_a_held_object_is_carried_without_reopening_the_gripper():
    plan = takeover_plan(_lay("pick_place"), grasped=True, remaining=0.0)
    assert isinstance(plan[0], Grip) and plan[0].value < 0  # closed before anything moves
    assert [s.role for s in plan if isinstance(s, Move)] == ["lift", "carry", "place", "retreat"]
    assert [s.value for s in plan if isinstance(s, Grip)] == [-1.0, 1.0]  # opened only at the target


def test_an_object_not_held_is_grasped_again_from_where_it_lies():
    plan = takeover_plan(_lay("move_to_aim"), grasped=False, remaining=0.0)
    assert isinstance(plan[0], Grip) and plan[0].value > 0  # open first: the policy may have closed on nothing
    assert plan[1:] == optimal_plan(_lay("move_to_aim"))


def test_a_slide_continues_for_what_remains():
    full = optimal_plan(_lay("push", direction=1.0, slide_distance=0.1))
    part = takeover_plan(_lay("push", direction=1.0, slide_distance=0.1), grasped=False, remaining=0.04)
    slide = lambda plan: next(s for s in plan if isinstance(s, Move) and s.role == "slide")  # noqa: E731
    contact = next(s for s in part if isinstance(s, Move) and s.role == "contact")
    assert abs((slide(part).pose[0] - contact.pose[0]) - (0.04 + 0.012)) < 1e-9  # remaining + the fingers' overshoot
    assert slide(full).pose[0] - slide(part).pose[0] > 0.05
    overshot = takeover_plan(_lay("pull", direction=-1.0), grasped=False, remaining=-0.01)
    assert abs(slide(overshot).pose[0] - next(s for s in overshot if getattr(s, "role", "") == "contact").pose[0]) < 0.02
