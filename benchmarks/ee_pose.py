"""What the arm controller's pose arithmetic on scalars (stages/collect/ee_pose.py) buys a simulator step, in one run.

One push env (the default scene, low-poly Panda, 64x64 RGB of both cameras at every step, as
collect records), random actions (speed does not depend on them). Each round runs ``--steps``
control steps with ManiSkill's arm controller, then as many with ``ScalarEEPoseController`` (the
same controller object, its class swapped; then the other order in the next round: ABBA), from the
same reset each time, and checks that both reach the same joint positions bit for bit. Prints each
round's steps/s and the median ratio scalar / ManiSkill.

    .venv/bin/python benchmarks/ee_pose.py [--steps 200] [--rounds 4]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def timed(env, cls, actions: np.ndarray) -> tuple[float, np.ndarray]:
    """(control steps/s, final joint positions (9,)) of ``actions`` from reset(seed=0) under ``cls``."""
    env.reset(seed=0)
    env.unwrapped.agent.controller.controllers["arm"].__class__ = cls
    t = time.perf_counter()
    for a in actions:
        env.step(a)
    rate = len(actions) / (time.perf_counter() - t)
    return rate, env.unwrapped.agent.robot.get_qpos().numpy()[0].copy()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=4)
    args = ap.parse_args()
    if args.steps < 1 or args.rounds < 1:
        ap.error("--steps and --rounds must be >= 1")
    torch.set_num_threads(1)  # what a collect or evaluation worker runs with

    from stages.collect.envs import DEFAULT_SCENE  # sets up Vulkan, then imports sapien
    from stages.collect.ee_pose import ScalarEEPoseController
    from stages.collect.sim import make_task_env
    from mani_skill.agents.controllers.pd_ee_pose import PDEEPoseController

    env = make_task_env("push", DEFAULT_SCENE)
    actions = np.random.default_rng(0).uniform(-1, 1, (args.steps, 7)).astype(np.float32)
    timed(env, PDEEPoseController, actions[:10])  # warm-up
    ratios = []
    for r in range(args.rounds):
        order = (PDEEPoseController, ScalarEEPoseController) if r % 2 == 0 else (ScalarEEPoseController, PDEEPoseController)
        got = {cls: timed(env, cls, actions) for cls in order}
        (slow, q_slow), (fast, q_fast) = got[PDEEPoseController], got[ScalarEEPoseController]
        if not np.array_equal(q_slow, q_fast):
            raise SystemExit(f"round {r + 1}: the two controllers reached different joint positions: {q_slow} vs {q_fast}")
        ratios.append(fast / slow)
        print(f"  round {r + 1}/{args.rounds}: ManiSkill's ee pose {slow:.1f}, scalar {fast:.1f} control steps/s: "
              f"ratio {fast / slow:.2f} (same joint positions)", flush=True)
    env.close()
    print(f"control steps/s of one push env (64x64 RGB x 2 cameras each step, 1 torch thread, this machine), "
          f"{args.steps} steps per measurement: ratio scalar / ManiSkill's ee pose median {statistics.median(ratios):.2f} "
          f"over {args.rounds} round(s), range {min(ratios):.2f}-{max(ratios):.2f}")


if __name__ == "__main__":
    main()
