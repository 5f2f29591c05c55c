"""Where a policy's placing episodes fail: how far each pick-and-place and move-to-aim episode gets.

    PYTHONPATH=. .venv/bin/python scripts/place_failure_probe.py <collect> <tokenize> <sft> [--rl RL]
        [--episodes 10] [--seed 1] [--splits ind] [--tasks pick_place move_to_aim] [--out FILE.jsonl]
        [--strips DIR] [--hide carpet container]

The policy acts closed loop (deterministic) on the evaluate stage's jobs (its scenes and initial
states; ``--seed 1`` draws states apart from the stage's, as ``scripts/evaluate_sft.py``), and after
every policy step the simulator's state is read: is the object grasped (ManiSkill's
``is_grasping``), lifted (its centre 2 cm above its resting height), over the target (its centre
within the container's inner radius or on the carpet); success is the task's own check. Each
episode is filed under the furthest phase it reached:

  never grasped -> grasped, never lifted -> lifted, never over the target -> over the target,
  not placed -> success (placed, resting and released)

and the table prints, per (split, task), how many episodes stopped at each phase, with the closest
the object came to the target (median over the episodes). ``--out`` keeps one row per episode;
``--strips DIR`` saves, for the first episode of each (split, task, phase), 8 third-view frames from
start to end (``DIR/<split>_<task>_<phase>.png``; every control step is rendered then, so it runs
slower): look at the failures before believing the counts. Each row also keeps how close the
gripper (ManiSkill's TCP) came to the object, ``reach_cm``, and to the target in xy, ``aim_cm``, and
how close the object came to the container in xy, ``container_cm`` (move to aim's distractor): a
policy that never grasps may stop short of the object or go somewhere else, and one that carries
the object may carry it to the wrong place. Where the policy first commands the gripper shut it
keeps the policy step, ``close_step``, the gripper's distance to the object, ``close_reach_cm``, and
its height above the object's centre, ``close_above_cm`` (None if it never closes): a grasp missed
by a centimetre, a grasp closed in the air, and no grasp tried look alike in the phase counts.
``--hide carpet`` / ``--hide container`` move that actor 20 cm under the table at every reset, after
the layout is drawn (same states; the target's xy is kept, so success is still judged against it):
the policy then acts on a scene without it, to ask whether what it sees there is what breaks the grasp.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo root: runs without PYTHONPATH=.

PHASES = ("never grasped", "grasped, never lifted", "lifted, never over the target", "over the target, not placed",
          "success")
LIFT = 0.02  # m above the object's resting height: off the table
HIDEABLE = ("carpet", "container")
UNDER_TABLE = -0.2  # m: the table's top is a 4 cm box below z=0; the carpet has no collision, the container is kinematic


@contextlib.contextmanager
def hidden(names):
    """Within the block, every task env moves the actors ``names`` (of ``HIDEABLE``) under the table at each
    reset, after its layout is drawn; xy kept, so the target's position and the states drawn are the same."""
    unknown = sorted(set(names) - set(HIDEABLE))
    if unknown:
        raise ValueError(f"cannot hide {unknown}; hideable: {list(HIDEABLE)}")
    from stages.collect.envs import RSTabletopEnv  # first: it sets up Vulkan before sapien is imported

    from mani_skill.utils.structs.pose import Pose

    original = RSTabletopEnv._initialize_episode

    def initialize(self, env_idx, options):
        original(self, env_idx, options)
        for name in names:
            actor = getattr(self, name, None)  # pick-and-place has no carpet
            if actor is not None:
                p = actor.pose.p.clone()  # (1, 3)
                p[:, 2] = UNDER_TABLE
                actor.set_pose(Pose.create_from_pq(p, actor.pose.q))

    RSTabletopEnv._initialize_episode = initialize
    try:
        yield
    finally:
        RSTabletopEnv._initialize_episode = original


def furthest_phase(steps: list[dict], success: bool) -> str:
    """The furthest of ``PHASES`` an episode reached, from its per-step flags (grasped, lifted, over)."""
    if success:
        return PHASES[4]
    reached = 0
    for s in steps:
        if s["grasped"]:
            reached = max(reached, 1)
        if s["grasped"] and s["lifted"]:
            reached = max(reached, 2)
        if reached >= 2 and s["over"]:
            reached = max(reached, 3)
    return PHASES[reached]


def state_of(env) -> dict:
    """The placing task's state after a step of ``env`` (a ``SimTaskEnv``): grasped, lifted, over, the object's
    xy distance to the target and the gripper's (TCP's) distance to the object."""
    u = env.env.unwrapped
    p = u.obj.pose.p[0]  # (3,) world position of the object's centre
    dist = float(np.linalg.norm((p[:2] - u._target_xy()[0]).numpy()))
    tcp = u.agent.tcp_pose.p[0]  # (3,)
    reach = float(np.linalg.norm((tcp - p).numpy()))
    aim = float(np.linalg.norm((tcp[:2] - u._target_xy()[0]).numpy()))
    container = float(np.linalg.norm((p[:2] - u.container.pose.p[0, :2]).numpy()))
    return {"grasped": bool(u.agent.is_grasping(u.obj)[0]), "lifted": bool(p[2] > u.obj_rest_z + LIFT),
            "over": dist < float(u._target_radius()), "dist": dist, "reach": reach, "aim": aim,
            "container": container, "above": float(tcp[2] - p[2])}


def first_close(steps: list[dict], grippers: list[float]) -> dict:
    """Where the policy first commands the gripper shut (gripper action < 0, ``stages.collect.actions``):
    the policy step, the TCP's distance to the object and its height above the object's centre then
    (cm; the state the command was issued in). All None if it never does."""
    k = next((i for i, g in enumerate(grippers) if g < 0), None)
    if k is None:
        return {"close_step": None, "close_reach_cm": None, "close_above_cm": None}
    return {"close_step": k, "close_reach_cm": round(100 * steps[k]["reach"], 2),
            "close_above_cm": round(100 * steps[k]["above"], 2)}


def run(job, frames: bool = False) -> list[dict]:
    """One row per seed of ``job``: phase, success, steps, the closest the object came to the target
    (and with ``frames`` its third-view frames, (control steps + 1, H, W, 3) uint8)."""
    from stages.evaluate.episodes import _policy_for, _sim_for, _spec
    from stages.sft.policy import act

    env, model, spec = _sim_for(job), _policy_for(job), _spec(job)
    env.keep_frames = frames
    rows = []
    for seed in job.seeds:
        obs, info = env.reset(seed=seed, options={"spec": spec})
        success, steps, grippers = bool(info["success"]), [state_of(env)], []
        while not success and len(steps) <= job.max_steps:
            action = act(model, {k: v[None] for k, v in obs.items()})[0]  # (7,)
            grippers.append(float(action[6]))
            obs, _, terminated, truncated, info = env.step(action)
            steps.append(state_of(env))
            success = success or bool(info["success"])
            if terminated or truncated:
                break
        rows.append({"task": job.task, "scene_id": job.scene["scene_id"], "split": job.split, "seed": int(seed),
                     "success": success, "steps": len(steps) - 1, "phase": furthest_phase(steps, success),
                     "closest_cm": round(100 * min(s["dist"] for s in steps), 2),
                     "reach_cm": round(100 * min(s["reach"] for s in steps), 2),
                     "aim_cm": round(100 * min(s["aim"] for s in steps), 2),
                     "container_cm": round(100 * min(s["container"] for s in steps), 2),
                     **first_close(steps, grippers)})
        if frames:
            rows[-1]["frames"] = np.stack([f[0] for f in env.frames])
    env.keep_frames = False
    return rows


def save_strips(rows: list[dict], out: Path) -> list[Path]:
    """The first episode of each (split, task, phase) as a strip of 8 frames, start to end."""
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    saved = {}
    for r in rows:
        name = f"{r['split']}_{r['task']}_{r['phase'].replace(', ', '_').replace(' ', '_')}.png"
        if name in saved:
            continue
        picks = np.linspace(0, len(r["frames"]) - 1, 8).round().astype(int)
        strip = np.concatenate([r["frames"][i] for i in picks], axis=1)  # (H, 8W, 3)
        Image.fromarray(strip).resize((strip.shape[1] * 2, strip.shape[0] * 2), Image.NEAREST).save(out / name)
        saved[name] = out / name
    return list(saved.values())


def table(rows: list[dict]) -> str:
    """Markdown: per (split, task), the episodes that stopped at each phase, and the median closest distance."""
    groups = collections.defaultdict(list)
    for r in rows:
        groups[(r["split"], r["task"])].append(r)
    head = ("| split | task | episodes | " + " | ".join(PHASES)
            + " | closest to the target, median cm | gripper closest to the object, median cm |")
    lines = [head, "|" + "---|" * (len(PHASES) + 5)]
    for (split, task), rs in sorted(groups.items()):
        counts = collections.Counter(r["phase"] for r in rs)
        lines.append(f"| {split} | {task} | {len(rs)} | " + " | ".join(str(counts[p]) for p in PHASES)
                     + f" | {np.median([r['closest_cm'] for r in rs]):.1f} | {_median(rs, 'reach_cm')} |")
    return "\n".join(lines)


def _median(rows: list[dict], key: str) -> str:
    """The median of ``key`` over ``rows`` to 0.1, or "-" where the rows predate it."""
    values = [r[key] for r in rows if key in r]
    return f"{np.median(values):.1f}" if values else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in ("collect", "tokenize", "sft"):
        ap.add_argument(name, type=Path)
    ap.add_argument("--rl", type=Path, default=None, help="probe this rl artifact's PPO policy instead of SFT")
    ap.add_argument("--episodes", type=int, default=10, help="episodes per (task, split)")
    ap.add_argument("--seed", type=int, default=1, help="the evaluate stage's seed (1: states apart from its own)")
    ap.add_argument("--splits", default="ind")
    ap.add_argument("--tasks", nargs="+", default=["pick_place", "move_to_aim"], choices=["pick_place", "move_to_aim"])
    ap.add_argument("--max-steps", type=int, default=75)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--strips", type=Path, default=None, help="save a frame strip per (split, task, phase) here")
    ap.add_argument("--hide", nargs="+", default=[], choices=HIDEABLE, help="move these under the table at each reset")
    args = ap.parse_args()

    from stages.evaluate import Config
    from stages.evaluate.jobs import build_jobs
    from stages.sft import read_policy_json

    info = read_policy_json(args.sft)
    missing = [t for t in args.tasks if t not in info["tasks"]]
    if missing:
        raise SystemExit(f"the policy of {args.sft} was not trained on {missing} (its tasks: {info['tasks']})")
    dirs = {"collect": args.collect, "tokenize": args.tokenize, "sft": args.sft, "rl": args.rl or Path("/nonexistent")}
    ctx = SimpleNamespace(input=lambda name: dirs[name], device="cpu")
    cfg = Config(episodes=args.episodes, seed=args.seed, policies=["ppo" if args.rl else "sft"],
                 splits=args.splits.split(","), videos=False, max_steps=args.max_steps, snapshot_episodes=0)
    jobs = [j for j in build_jobs(ctx, cfg, {"tasks": info["tasks"], "frame_skip": info["frame_skip"]})
            if j.task in args.tasks]
    rows = []
    with hidden(args.hide):
        for i, job in enumerate(jobs):
            rows += run(job, frames=args.strips is not None)
            print(f"  job {i + 1}/{len(jobs)}: {job.task} {job.split} {job.scene['scene_id']}", flush=True)
    if args.strips is not None:
        print(f"frame strips: {len(save_strips(rows, args.strips))} in {args.strips}")
    rows = [{k: v for k, v in r.items() if k != "frames"} for r in rows]
    if args.out is not None:
        args.out.write_text("".join(json.dumps(r) + "\n" for r in rows))
    print(table(rows))


if __name__ == "__main__":
    main()
