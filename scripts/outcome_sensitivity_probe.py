"""How much of an open-loop action sequence's outcome does the first frame decide?

Imagined-success precision (issue 13's target 3) replays a policy's imagined actions open loop in
the simulator from the same initial state. A world model reads that state from 64 x 64 frames, so
it knows the object's position only to some resolution; if moving the object by less than that
flips the outcome of the *same* action sequence, no world model reading these frames can predict
the replay's success, and precision has a ceiling below 1 that is the simulator's, not the model's.

This probe measures that sensitivity on the collect stage's own demonstrations (MPLib's optimal
plans, ``stages.collect.worker.record_episode``): for each (task, scene, seed) it records the plan,
checks that the recorded actions replay to success from ``reset(seed)``, then replays them again
with the object moved by ``delta`` cm in the table plane (``--directions`` evenly spaced
directions, a random phase per episode) before the first step, everything else as reset left it
(the goal, the container, the arm). Printed per task and ``delta``: the replays that still succeed
among those whose undisturbed replay succeeded (a Wilson interval), and how far one pixel of the
third view is on the table at the object's start (the object's position and the same moved 1 cm,
projected with the third camera's parameters).

Measured (2026-12-04, 2-core AMD EPYC, ``--seeds 8``, IND, 128 replays per column, 4 min): 0.5 cm
128/128, 1 cm 127/128, 2 cm 94/128 = 0.73 [0.65, 0.80]; one pixel is ~0.76 cm on the table. So a
plan's outcome is fixed by the first frame to about a pixel (docs/RESULTS.md notebook). A seed-0 SFT
policy's own closed-loop successes (``--artifacts``, 16 environments x 4 seeds): IND 0.77 / 0.61 /
0.30 at 0.5 / 1 / 2 cm, OOD 0.91 / 0.87 / 0.51: a learned policy's open-loop sequences are far more
sensitive than plans.

    PYTHONPATH=. .venv/bin/python scripts/outcome_sensitivity_probe.py [--seeds 6] [--deltas 0.5 1 2]
        [--directions 4] [--split ind] [--noise 0.0] [--tasks ...] [--out F.json]
        [--artifacts COLLECT TOKENIZE SFT [--policy P] [--envs 16] [--steps 75]]

``--artifacts COLLECT TOKENIZE SFT`` replaces the demonstrations by a policy's own
successes (``--policy``: a policy file, default the SFT policy): it acts closed loop in the simulator
(deterministic, ``stages.common.sim_env.SimTaskEnv`` with the policy's frame skip, as the
imagined-success check replays) on ``--envs`` environments of ``--split``, seeds 0..``--seeds``-1
each, and the action sequences that succeed are replayed with the object moved, policy step by policy
step, as the rl stage replays imagined ones.

``--noise`` adds Gaussian noise of that std (normalised action units, arm dimensions only) to the
recorded actions, drawn once per episode, so the sequence is less like a plan and more like a
policy's (the undisturbed replay of the noisy actions is then the reference).
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from stages.collect.envs import DEFAULT_SCENE  # noqa: F401  (sets up Vulkan, then imports sapien)
from stages.collect.execute import PlanFailure
from stages.collect.sim import TASKS, default_catalog
from stages.collect.worker import _sim, record_episode
from stages.evaluate.stats import wilson


def replay_moved(env, seed: int, actions: np.ndarray, offset_m: tuple[float, float]) -> bool:
    """``actions`` (T, 7) open loop from ``reset(seed)`` with the object moved by ``offset_m`` (x, y)
    metres first; True if the task succeeds at any step."""
    env.reset(seed=seed)
    if offset_m != (0.0, 0.0):
        move_object(env, offset_m)
    for a in actions:
        _, _, _, _, info = env.step(np.asarray(a, np.float32)[None])
        if bool(info["success"].reshape(-1)[0]):
            return True
    return False


def move_object(env, offset_m: tuple[float, float]) -> None:
    """Move the just-reset scene's object by ``offset_m`` (x, y) metres in the table plane, at rest."""
    import torch
    from mani_skill.utils.structs.pose import Pose

    obj = env.unwrapped.obj
    p, q = obj.pose.p.clone(), obj.pose.q.clone()  # (1, 3), (1, 4)
    p[:, 0] += offset_m[0]
    p[:, 1] += offset_m[1]
    obj.set_pose(Pose.create_from_pq(p=p, q=q))
    obj.set_linear_velocity(torch.zeros_like(p))
    obj.set_angular_velocity(torch.zeros_like(p))


def policy_sequences(args):
    """The policy's closed-loop episodes in the simulator, ({task, scene, seed, spec, actions, success}
    per episode, the simulator)."""
    import json as json_

    from stages.collect.catalog import read_scenes_json
    from stages.collect.dataset import read_sim_facts
    from stages.common.environments import pick_environments
    from stages.common.sim_env import SimSpec, SimTaskEnv
    from stages.goals.environments import list_environments
    from stages.sft import TEXT_EMBEDDINGS, read_policy_json
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, act, load_policy
    from stages.tokenize.tokenizer import load_tokenizer

    collect, tokenize, sft = args.artifacts
    info = read_policy_json(sft)  # frame_skip (= the world model's), tasks, observation layout
    tok = load_tokenizer(tokenize, "cpu")
    obs_fn = ObservationFn.for_policy(tok, json_.loads((sft / TEXT_EMBEDDINGS).read_text()), info)
    scenes, facts = read_scenes_json(collect / "scenes.json"), read_sim_facts(collect)
    picked = pick_environments([e for e in list_environments(collect)
                                if e.split == args.split and e.task in info["tasks"]], args.envs)
    specs = [SimSpec(e.task, scenes[e.scene_id].to_dict(), e.instruction) for e in picked]
    sim = SimTaskEnv(specs, obs_fn, max_steps=args.steps, action_repeat=int(info["frame_skip"]),
                     image_size=facts.image_size, robot_mesh=facts.robot_mesh)
    policy = load_policy(args.policy or sft / POLICY_FILE, "cpu")
    out = []
    for spec in specs:
        for seed in range(args.seeds):
            obs, _ = sim.reset(seed=seed, options={"spec": spec})
            actions, success = [], False
            for _ in range(args.steps):
                a = act(policy, {k: v[None] for k, v in obs.items()})[0]  # (7,)
                obs, _, success, truncated, _ = sim.step(a)
                actions.append(a)
                if success or truncated:
                    break
            out.append({"task": spec.task, "scene": spec.scene["scene_id"], "seed": seed, "spec": spec,
                        "actions": np.asarray(actions), "success": bool(success)})
    return out, sim


def replay_policy_moved(sim, spec, seed: int, actions: np.ndarray, offset_m: tuple[float, float]) -> bool:
    """A policy's actions (T, 7) open loop, policy step by policy step, from ``sim.reset(seed)`` with
    the object moved; True if the task succeeds at any step."""
    sim.reset(seed=seed, options={"spec": spec})
    if offset_m != (0.0, 0.0):
        move_object(sim.env, offset_m)
    for a in actions:
        _, _, success, _, _ = sim.step(a)
        if success:
            return True
    return False


def pixel_cm(env, seed: int | None) -> float:
    """Centimetres on the table per pixel of the third view at the object's start: the object's
    position and the same moved 1 cm in x and in y, projected with the camera's parameters, the mean
    of the two shifts (``seed`` None: the scene as it is)."""
    if seed is not None:
        env.reset(seed=seed)
    u = env.unwrapped
    params = u._sensors["third"].get_params()
    k = params["intrinsic_cv"][0].cpu().numpy()  # (3, 3)
    ext = params["extrinsic_cv"][0].cpu().numpy()  # (3, 4) world -> camera (OpenCV)
    p = u.obj.pose.p[0].cpu().numpy()  # (3,)

    def pixel(x: np.ndarray) -> np.ndarray:
        c = ext[:, :3] @ x + ext[:, 3]
        uvw = k @ c
        return uvw[:2] / uvw[2]

    shifts = [np.linalg.norm(pixel(p + d) - pixel(p)) for d in (np.array([0.01, 0, 0]), np.array([0, 0.01, 0]))]
    return 1.0 / float(np.mean(shifts))


def demo_sequences(args):
    """The collect stage's optimal plans, one IND (or OOD) scene per (task, seed), as replays:
    yields (row fields, replay(offset) -> bool, cm per pixel)."""
    scenes = [s for s in default_catalog().values() if s.split == args.split]
    for task in args.tasks:
        env, runner, state = _sim(task, 64, "lowpoly", 400)
        for seed in range(args.seeds):
            scene = scenes[(seed * 7 + TASKS.index(task)) % len(scenes)].to_dict()
            try:
                rec = record_episode(env, runner, state, scene, "optimal", seed)
            except PlanFailure:
                continue
            rng = np.random.default_rng([seed, TASKS.index(task)])
            actions = rec.action.copy()
            if args.noise:
                actions[:, :6] = np.clip(actions[:, :6] + rng.normal(0, args.noise, actions[:, :6].shape), -1, 1)
            yield ({"task": task, "scene": scene["scene_id"], "seed": seed},
                   lambda off, env=env, seed=seed, actions=actions: replay_moved(env, seed, actions, off),
                   pixel_cm(env, seed))


def policy_replays(args):
    """The policy's closed-loop successes and failures, as ``demo_sequences`` yields them."""
    episodes, sim = policy_sequences(args)
    print(f"  the policy succeeded closed loop in {sum(e['success'] for e in episodes)} of {len(episodes)} "
          "episodes", flush=True)
    for e in episodes:
        actions = e["actions"]
        if args.noise:
            rng = np.random.default_rng([e["seed"], 7])
            actions = actions.copy()
            actions[:, :6] = np.clip(actions[:, :6] + rng.normal(0, args.noise, actions[:, :6].shape), -1, 1)
        replay = (lambda off, spec=e["spec"], seed=e["seed"], actions=actions:
                  replay_policy_moved(sim, spec, seed, actions, off))
        sim.reset(seed=e["seed"], options={"spec": e["spec"]})  # the episode's start, for the pixel scale
        yield {"task": e["task"], "scene": e["scene"], "seed": e["seed"]}, replay, pixel_cm(sim.env, None)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=6,
                    help="episodes per task (demonstrations: one scene each) or per environment (--artifacts)")
    ap.add_argument("--deltas", type=float, nargs="+", default=[0.5, 1.0, 2.0], help="object moves, cm")
    ap.add_argument("--directions", type=int, default=4)
    ap.add_argument("--split", default="ind", choices=["ind", "ood"])
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS), help="demonstrations of these tasks")
    ap.add_argument("--artifacts", type=Path, nargs=3, default=None, metavar=("COLLECT", "TOKENIZE", "SFT"),
                    help="replay a policy's own successes instead of the demonstrations")
    ap.add_argument("--policy", type=Path, default=None, help="with --artifacts: a policy file (default SFT's)")
    ap.add_argument("--envs", type=int, default=16, help="with --artifacts: environments of --split")
    ap.add_argument("--steps", type=int, default=75, help="with --artifacts: policy steps per episode")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.seeds < 1 or args.directions < 1:
        ap.error("--seeds and --directions must be >= 1")
    source = policy_replays(args) if args.artifacts else demo_sequences(args)
    what = f"policy {args.policy or 'SFT'}" if args.artifacts else "demonstrations"
    rows, t0 = [], time.perf_counter()
    for fields, replay, scale in source:
        base = replay((0.0, 0.0))
        phase = np.random.default_rng([fields["seed"], len(rows)]).uniform(0, 2 * math.pi)
        mine = []
        for delta in args.deltas:
            for k in range(args.directions):
                ang = phase + 2 * math.pi * k / args.directions
                off = (delta / 100 * math.cos(ang), delta / 100 * math.sin(ang))
                mine.append({**fields, "base": base, "cm_per_pixel": scale, "delta_cm": delta, "dir": k,
                             "success": replay(off) if base else None})
        rows += mine
        print(f"  {fields['task']} seed {fields['seed']} ({fields['scene']}, {scale:.2f} cm per pixel): "
              f"undisturbed {base}" + ("" if not base else ", moved " + " ".join(
                  f"{d}cm {sum(r['success'] for r in mine if r['delta_cm'] == d)}/{args.directions}"
                  for d in args.deltas)) + f"  [{time.perf_counter() - t0:.0f} s]", flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")
    print(f"\nThe same actions ({what}) replayed with the object moved ({args.split}, noise {args.noise}, "
          f"{args.seeds} seeds, {args.directions} directions): successes among episodes whose undisturbed "
          "replay succeeded (95% Wilson interval)")
    print("| task | " + " | ".join(f"{d} cm" for d in args.deltas) + " | cm per pixel (median) |")
    print("|---|" + "---|" * (len(args.deltas) + 1))
    for task in [t for t in TASKS if any(r["task"] == t for r in rows)] + ["all"]:
        cells = []
        for d in args.deltas:
            sel = [r for r in rows if r["base"] and r["delta_cm"] == d and task in (r["task"], "all")]
            k, n = sum(r["success"] for r in sel), len(sel)
            _, lo, hi = wilson(k, n)
            cells.append(f"{k}/{n} = {k / max(n, 1):.2f} [{lo:.2f}, {hi:.2f}]")
        scales = [r["cm_per_pixel"] for r in rows if task in (r["task"], "all")]
        print(f"| {task} | " + " | ".join(cells) + f" | {np.median(scales) if scales else float('nan'):.2f} |")


if __name__ == "__main__":
    main()
