"""What the timed memory layout buys the world-model env, measured in one run: PPO steps/s (updates
included) of the env with the ``wm`` reward (every frame decoded, LPIPS to a goal) with the
tokenizer's decoder and the LPIPS network in the default layout, against the same env with the
layouts ``stages.common.precision.conv_layout`` chose by timing them on this CPU (channels-last
where it ran >= ``CHANNELS_LAST_GAIN`` x faster; always for bf16). The two envs share the world
model, policy architecture and PPO settings of ``benchmarks/rl_throughput.py`` (random weights:
speed does not depend on them) and are measured alternately, ``--rounds`` times, so a slow spell of
a noisy machine falls on both; each round's ratio and their median are printed.

    .venv/bin/python benchmarks/conv_layout.py [--steps 2048] [--num-envs 16] [--threads N] [--rounds 3] [--wm-dtype fp32]

The env runs fp32 by default: bf16 is channels-last whatever the timing says, so under bf16 (or an
``auto`` that resolves to it) both envs have the same layouts and the benchmark says so before timing.

The goal distance is built on ``--goals`` copies of the goal frame (the rl stage builds it on one
goal per environment of the goals artifact); its layout is timed on up to ``PROBE_FRAMES`` (32) of them.
"""
from __future__ import annotations

import argparse
import copy
import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rl_throughput import Setup, stage_threads, timed_learn  # noqa: E402

from stages.common import precision  # noqa: E402


def env_with_layouts(setup: Setup, args, timed: bool):
    """The ``wm``-reward env on its own copy of the tokenizer; ``timed`` False forces the default layouts."""
    gain = precision.CHANNELS_LAST_GAIN
    if not timed:
        precision.CHANNELS_LAST_GAIN = float("inf")  # no timing can reach it: fp32 stays default (bf16 is channels-last regardless)
    try:
        return setup.wm_env(0.02, args.num_envs, args.wm_dtype, tok=copy.deepcopy(setup.tok))
    finally:
        precision.CHANNELS_LAST_GAIN = gain


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=2048)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--goals", type=int, default=48)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--wm-dtype", choices=["fp32", "bf16", "auto"], default="fp32",
                    help="the env's precision (default fp32: the only one whose layout is timed)")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads (default: the rl stage's `threads`, what it runs with)")
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds must be >= 1, got {args.rounds}")
    if args.threads is None:
        args.threads = stage_threads()
    torch.set_num_threads(args.threads)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")

    setup = Setup("cpu")
    setup.goal = tuple(g.repeat(args.goals, 1, 1, 1) for g in setup.goal)  # (goals, 3, S, S) per view
    envs = {"default": env_with_layouts(setup, args, timed=False), "timed": env_with_layouts(setup, args, timed=True)}
    layouts = {name: (precision.layout_of(env.tok.net.decoder), precision.layout_of(env.reward.distance.net))
               for name, env in envs.items()}
    for name, (decoder, lpips) in layouts.items():
        print(f"  {name}: decoder {decoder}, LPIPS {lpips} ({envs[name].dtype})", flush=True)
    if layouts["default"] == layouts["timed"]:
        print(f"  both envs have the same layouts under {envs['timed'].dtype}: the ratio below measures noise only",
              flush=True)
    rates = []
    for r in range(args.rounds):
        a = timed_learn(envs["default"], args.steps, args.num_envs, "cpu")
        b = timed_learn(envs["timed"], args.steps, args.num_envs, "cpu")
        rates.append((a, b))
        print(f"  round {r + 1}/{args.rounds}: default layouts {a:.1f}, timed layouts {b:.1f} steps/s: ratio {b / a:.3f}",
              flush=True)
    ratios = [b / a for a, b in rates]
    print(f"world-model env with LPIPS, {args.num_envs} envs, {torch.get_num_threads()} torch thread(s), this machine: "
          f"timed / default layouts median {np.median(ratios):.3f}, range {min(ratios):.3f}-{max(ratios):.3f} "
          f"over {args.rounds} alternating round(s)")


if __name__ == "__main__":
    main()
