"""Waypoint plans: the essential waypoints of each task, and the paper's three suboptimal variants.

A plan is a list of steps, pure data (no simulator): ``Move(pose, label)`` (a TCP pose in the world
frame: xyz + quaternion wxyz) or ``Grip(value, steps)`` (open +1 / close -1 while holding still).
``execute.py`` turns each Move into an MPLib screw motion (RRTConnect as fallback).

Suboptimal kinds (paper §4.1), each derived from the optimal plan of the same episode:
  - ``waypoint_noise``: unrelated intermediate waypoints (random workspace positions, noisy
    rotations) inserted before the approach and before the transport/slide;
  - ``interpolate``: every essential motion split into several pieces through interpolated poses
    (same path, stop-and-go timing, longer episode);
  - ``grasp_disturb``: small pose disturbances (~1-2 cm, ~0.15 rad) just before the grasp / contact
    waypoint and the place waypoint; for push / pull, a sideways wobble (<= 0.9 cm) mid-slide.

One recovery kind (beyond the paper), a demonstration that errs first and then recovers:
  - ``recover``: pick & place, move to aim: the gripper first closes where SFT policies close by
    mistake, either in the air 2.5-5 cm above the grasp pose (their early close; it then reopens
    and goes on down to the grasp) or at the grasp height 5-6.5 cm beside the object
    (``grasp_miss``'s error; it then reopens, rises and completes the optimal plan from the
    pre-grasp pose). Push, pull: the closed fingers first come down beside the object
    (``grasp_miss``'s sideways offset, at the contact height), rise and complete the optimal plan
    from the pre-contact pose. It must succeed like any demonstration; SFT (``sft.kinds``) imitates
    it from the end of the mistake on, so it learns the way back, never the mistake.

Two failure kinds (beyond the paper), the world model's negatives, never a demonstration:
  - ``near_miss``: the optimal plan that misses at the end: the object is carried and released
    8-13 cm beside its target (pick & place, move to aim), or the slide stops after 15-60% of its
    distance (push, pull). Its last frames look like a finished demonstration but are not.
  - ``grasp_miss``: the optimal plan that misses at the start: the gripper descends and closes 5-6.5 cm
    beside the object (across the fingers' closing direction, so neither finger touches it) and then
    carries nothing to the target (pick & place, move to aim), or the closed fingers slide past the
    object 5-6.5 cm to its side (push, pull). Without it every recorded contact moves the object, and
    the world models trained so far imagined the object following a gripper that closed beside it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.common.proprio import quat_to_matrix

SUBOPTIMAL_KINDS = ("waypoint_noise", "interpolate", "grasp_disturb")
FAILURE_KINDS = ("near_miss", "grasp_miss")
RECOVERY_KINDS = ("recover",)
KINDS = ("optimal", *SUBOPTIMAL_KINDS, *FAILURE_KINDS, *RECOVERY_KINDS)  # an index seeds a kind's rng: append only


@dataclass(frozen=True)
class Move:
    pose: tuple  # (7,) world-frame TCP pose, xyz + quaternion wxyz
    label: str = "essential"  # essential | noise | interp | disturb
    role: str = ""  # for essential moves: pre | grasp | lift | carry | place | retreat | contact | slide


@dataclass(frozen=True)
class Grip:
    value: float  # +1 open, -1 close
    steps: int = 8
    label: str = "essential"


@dataclass(frozen=True)
class Layout:
    """What a plan needs to know about the episode's initial state (world frame, metres)."""

    task: str
    obj_p: tuple  # object centre xyz
    obj_half: float
    grasp_q: tuple  # TCP orientation for a top-down grasp (wxyz)
    down_q: tuple  # the TCP's initial (top-down) orientation (wxyz)
    target_p: tuple = (0.0, 0.0, 0.0)  # where the object goes: container / carpet centre, or slide goal
    place_z: float = 0.0  # TCP height when releasing the object at the target
    direction: float = 1.0  # slide direction along x (push +1, pull -1)
    slide_distance: float = 0.1
    extra: dict = field(default_factory=dict)


def _pose(p, q) -> tuple:
    return tuple(float(v) for v in (*p, *q))


def optimal_plan(lay: Layout) -> list:
    """The essential waypoints of the task."""
    p = np.asarray(lay.obj_p, dtype=float)
    if lay.task in ("pick_place", "move_to_aim"):
        grasp_z = max(p[2], 0.012)
        grasp = np.array([p[0], p[1], grasp_z])
        carry_z = 0.16
        tgt = np.asarray(lay.target_p, dtype=float)
        return [
            Move(_pose(grasp + [0, 0, 0.08], lay.grasp_q), role="pre"),
            Move(_pose(grasp, lay.grasp_q), role="grasp"),
            Grip(-1.0, 8),
            Move(_pose([p[0], p[1], carry_z], lay.grasp_q), role="lift"),
            Move(_pose([tgt[0], tgt[1], carry_z], lay.grasp_q), role="carry"),
            Move(_pose([tgt[0], tgt[1], lay.place_z], lay.grasp_q), role="place"),
            Grip(1.0, 6),
            Move(_pose([tgt[0], tgt[1], lay.place_z + 0.08], lay.grasp_q), role="retreat"),
        ]
    if lay.task in ("push", "pull"):
        d = lay.direction
        z = float(np.clip(p[2], 0.015, 0.025))
        contact = np.array([p[0] - d * (lay.obj_half + 0.02), p[1], z])
        # the closed fingers stop ~1 cm short of the object's centre line: overshoot by that much
        end = contact + [d * (lay.slide_distance + 0.012), 0, 0]
        return [
            Grip(-1.0, 6),
            Move(_pose(contact + [0, 0, 0.08], lay.down_q), role="pre"),
            Move(_pose(contact, lay.down_q), role="contact"),
            Move(_pose(end, lay.down_q), role="slide"),
            Move(_pose(end + [-d * 0.02, 0, 0.08], lay.down_q), role="retreat"),
        ]
    raise ValueError(f"unknown task {lay.task!r}")


def _rot_noise(q, rng, sigma: float) -> tuple:
    """q rotated by a random axis-angle with N(0, sigma) angle (world frame)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.normal(0, sigma)
    dq = np.array([np.cos(angle / 2), *(np.sin(angle / 2) * axis)])
    w1, x1, y1, z1 = dq
    w2, x2, y2, z2 = q
    return (
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    )


def _random_workspace_pose(q, rng, rot_sigma: float) -> tuple:
    p = [rng.uniform(-0.12, 0.15), rng.uniform(-0.2, 0.2), rng.uniform(0.12, 0.26)]
    return _pose(p, _rot_noise(q, rng, rot_sigma))


def _slerp(q0, q1, t: float) -> np.ndarray:
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + t * (q1 - q0)
    else:
        th = np.arccos(dot)
        q = (np.sin((1 - t) * th) * q0 + np.sin(t * th) * q1) / np.sin(th)
    return q / np.linalg.norm(q)


def suboptimal_plan(opt: list, kind: str, rng: np.random.Generator, *, rot_sigma: float = 0.25,
                    n_interp: int = 2, disturb_pos: float = 0.015, disturb_rot: float = 0.15) -> list:
    """The optimal plan ``opt`` perturbed by ``kind`` (one of KINDS)."""
    if kind == "optimal":
        return list(opt)
    if kind == "near_miss":
        return near_miss_plan(opt, rng)
    if kind == "grasp_miss":
        return grasp_miss_plan(opt, rng)
    if kind == "recover":
        return recover_plan(opt, rng)
    out: list = []
    prev_pose = None
    for step in opt:
        if isinstance(step, Move):
            if kind == "waypoint_noise" and step.role in ("pre", "carry"):
                for _ in range(int(rng.integers(1, 3))):
                    out.append(Move(_random_workspace_pose(step.pose[3:], rng, rot_sigma), label="noise"))
            elif kind == "interpolate" and prev_pose is not None:
                a, b = np.asarray(prev_pose), np.asarray(step.pose)
                for k in range(1, n_interp + 1):
                    t = k / (n_interp + 1)
                    out.append(Move(_pose(a[:3] + t * (b[:3] - a[:3]), _slerp(a[3:], b[3:], t)), label="interp"))
            elif kind == "grasp_disturb" and step.role in ("grasp", "contact", "place"):
                p = np.asarray(step.pose[:3])
                off = rng.uniform(-disturb_pos, disturb_pos, size=3)
                off[2] = abs(off[2]) + 0.01  # disturb from above so the fingers do not hit the object
                if step.role == "contact":  # stay behind the object along the slide direction
                    off[0] = -abs(off[0]) * np.sign(opt_direction(opt))
                out.append(Move(_pose(p + off, _rot_noise(step.pose[3:], rng, disturb_rot)), label="disturb"))
            elif kind == "grasp_disturb" and step.role == "slide":
                # mid-slide, a sideways wobble that keeps contact: lifting the fingers here would
                # let a low object slip under them and change how far it goes
                a, b = np.asarray(prev_pose[:3]), np.asarray(step.pose[:3])
                p = a + rng.uniform(0.3, 0.7) * (b - a) + [0.0, rng.uniform(-disturb_pos, disturb_pos) * 0.6, 0.0]
                out.append(Move(_pose(p, _rot_noise(step.pose[3:], rng, disturb_rot * 0.5)), label="disturb"))
            elif kind not in KINDS:
                raise ValueError(f"unknown trajectory kind {kind!r}; expected one of {KINDS}")
            prev_pose = step.pose
        out.append(step)
    return out


def near_miss_plan(opt: list, rng: np.random.Generator, *, offset: tuple = (0.08, 0.13),
                   slide_fraction: tuple = (0.15, 0.6)) -> list:
    """``opt`` that ends beside its goal: transport waypoints shifted sideways, or the slide cut short."""
    moves = {s.role: s for s in opt if isinstance(s, Move)}
    out: list = []
    if "slide" in moves:  # push / pull: stop the slide early, retreat from where it stopped
        a, b = np.asarray(moves["contact"].pose[:3]), np.asarray(moves["slide"].pose[:3])
        shift = (1.0 - rng.uniform(*slide_fraction)) * (a - b)  # (3,) back towards the contact point
    else:  # pick & place, move to aim: carry, place and retreat beside the target
        angle = rng.uniform(0.0, 2.0 * np.pi)
        shift = rng.uniform(*offset) * np.array([np.cos(angle), np.sin(angle), 0.0])
    moved = ("slide", "retreat") if "slide" in moves else ("carry", "place", "retreat")
    for step in opt:
        if isinstance(step, Move) and step.role in moved:
            step = Move(_pose(np.asarray(step.pose[:3]) + shift, step.pose[3:]), label=step.label, role=step.role)
        out.append(step)
    return out


def grasp_miss_plan(opt: list, rng: np.random.Generator, *, offset: tuple = (0.05, 0.065)) -> list:
    """``opt`` whose grasp / contact lands beside the object: the approach shifted sideways, the rest as planned.

    Pick & place, move to aim: pre, grasp and lift move ``offset`` metres along the grasp frame's x
    axis (horizontal, across the closing direction, its y axis), so the fingers close in the air
    beside the object and carry nothing. Push, pull: pre, contact, slide and retreat move sideways
    (world y, across the slide), so the closed fingers pass beside the object. The 5 cm lower bound
    is 2 cm more than the largest object's half extent (3 cm); that the object stays where it was is
    checked in the simulator (tests/collect/test_sim.py).
    """
    moves = {s.role: s for s in opt if isinstance(s, Move)}
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if "slide" in moves:
        side = np.array([0.0, 1.0, 0.0])
        moved = ("pre", "contact", "slide", "retreat")
    else:
        side = quat_to_matrix(moves["grasp"].pose[3:])[:, 0] * [1.0, 1.0, 0.0]  # (3,) the grasp frame's x axis
        side /= max(np.linalg.norm(side), 1e-9)
        moved = ("pre", "grasp", "lift")
    shift = sign * rng.uniform(*offset) * side  # (3,) metres, horizontal
    out: list = []
    for step in opt:
        if isinstance(step, Move) and step.role in moved:
            step = Move(_pose(np.asarray(step.pose[:3]) + shift, step.pose[3:]), label=step.label, role=step.role)
        out.append(step)
    return out


def recover_plan(opt: list, rng: np.random.Generator, *, above: tuple = (0.025, 0.05),
                 offset: tuple = (0.05, 0.065), rise: float = 0.08) -> list:
    """``opt`` preceded by a mistake and its correction (module docstring, ``recover``).

    The mistake's steps are labelled ``err`` (moves with role ``err``): the recording starts its
    demonstration proper after them (``execute.Recording.demo_from``), so SFT imitates the way back
    (labelled ``recover``) and never the mistake itself. A mistake beside the object is approached
    from ``rise`` metres straight above it and left ``rise`` metres straight up before the plan
    returns to the pre-grasp / pre-contact pose, so fingers beside the object never sweep through
    it; after an early close above the object the fingers reopen and the plan goes on straight down
    to the grasp. Pick & place and move to aim draw the early close or the sideways miss with equal
    odds.
    """
    moves = {s.role: s for s in opt if isinstance(s, Move)}
    head = opt.index(moves["pre"]) + 1  # the optimal plan up to and including the pre pose
    target = moves["contact" if "slide" in moves else "grasp"]  # where the mistake is made instead
    t, q = np.asarray(target.pose[:3]), target.pose[3:]
    if "slide" in moves:  # push / pull: the closed fingers come down beside the object (world y)
        wrong = t + [0.0, (1.0 if rng.random() < 0.5 else -1.0) * rng.uniform(*offset), 0.0]
        mistake = [Move(_pose(wrong + [0, 0, rise], q), label="err", role="err"), Move(_pose(wrong, q), label="err", role="err")]
        back = [Move(_pose(wrong + [0, 0, rise], q), label="recover", role="recover"), moves["pre"]]
    elif rng.random() < 0.5:  # pick & place, move to aim: the early close, in the air straight below pre
        wrong = t + [0.0, 0.0, rng.uniform(*above)]
        mistake = [Move(_pose(wrong, q), label="err", role="err"), Grip(-1.0, 8, label="err")]
        back = [Grip(1.0, 6, label="recover")]  # reopen; the grasp pose is straight below
    else:  # the sideways miss: across the fingers' closing direction, as grasp_miss_plan does, from above
        x = quat_to_matrix(q)[:, 0] * [1.0, 1.0, 0.0]  # (3,) the grasp frame's x axis, horizontal
        wrong = t + (1.0 if rng.random() < 0.5 else -1.0) * rng.uniform(*offset) * x / max(np.linalg.norm(x), 1e-9)
        mistake = [Move(_pose(wrong + [0, 0, rise], q), label="err", role="err"), Move(_pose(wrong, q), label="err", role="err"),
                   Grip(-1.0, 8, label="err")]
        back = [Grip(1.0, 6, label="recover"), Move(_pose(wrong + [0, 0, rise], q), label="recover", role="recover"),
                moves["pre"]]
    return [*opt[:head], *mistake, *back, *opt[head:]]


def opt_direction(opt: list) -> float:
    """+1 if the plan's slide moves along +x, -1 otherwise (pick plans: +1)."""
    moves = {s.role: s for s in opt if isinstance(s, Move)}
    if "slide" in moves and "contact" in moves:
        return float(np.sign(moves["slide"].pose[0] - moves["contact"].pose[0]) or 1.0)
    return 1.0
