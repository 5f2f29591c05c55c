"""What the bf16 temporal KV cache buys the world-model env, measured in one run: env steps/s of the
env with the ``wm`` reward (every frame decoded, LPIPS to a goal), stepped with random actions and no
PPO, its rollout's KV cache in fp32 against bf16. Both run the world model under the same
``--wm-dtype`` autocast (bf16 is where the choice matters: autocast reads the cache in bf16 either
way), share the benchmarks/rl_throughput.py setup (random weights: speed does not depend on them),
and alternate in ABBA order ``--rounds`` times; each round prints its ratio and whether both caches
gave identical observations and rewards, then the median.

    .venv/bin/python benchmarks/kv_cache.py [--steps 96] [--num-envs 16] [--threads N] [--rounds 8] [--wm-dtype bf16]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rl_throughput import Setup, stage_threads  # noqa: E402


def stepped(env, setup: Setup, cache: torch.dtype, steps: int) -> tuple[float, list]:
    """Env steps/s of ``steps`` random-action steps from a fresh reset with a ``cache``-dtype KV cache,
    and the (codes, rewards) of every step."""
    env.roll = setup.wm.rollout(env.num_envs, seed=0, cache_dtype=cache)
    env.rng = np.random.default_rng(0)
    rng = np.random.default_rng(0)
    env.reset()
    out = []
    t = time.perf_counter()
    for _ in range(steps):
        env.step_async(rng.uniform(-1, 1, (env.num_envs, 7)).astype(np.float32))
        obs, rew, _, _ = env.step_wait()
        out.append((obs["codes"].copy(), rew.copy()))
    return steps * env.num_envs / (time.perf_counter() - t), out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=96)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--wm-dtype", choices=["fp32", "bf16"], default="bf16")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads (default: the rl stage's `threads`, what it runs with)")
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds must be >= 1, got {args.rounds}")
    torch.set_num_threads(args.threads or stage_threads())
    os.environ.setdefault("HF_HUB_OFFLINE", "1")

    setup = Setup("cpu")
    env = setup.wm_env(0.02, args.num_envs, args.wm_dtype)
    caches = {"fp32": torch.float32, "bf16": torch.bfloat16}
    stepped(env, setup, torch.bfloat16, 4)  # warm-up
    ratios = []
    for r in range(args.rounds):
        order = ("fp32", "bf16") if r % 2 == 0 else ("bf16", "fp32")
        res = {name: stepped(env, setup, caches[name], args.steps) for name in order}
        same = all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(res["fp32"][1], res["bf16"][1]))
        ratios.append(res["bf16"][0] / res["fp32"][0])
        print(f"  round {r + 1}/{args.rounds} ({order[0]} first): fp32 cache {res['fp32'][0]:.1f}, bf16 cache "
              f"{res['bf16'][0]:.1f} env steps/s: ratio {ratios[-1]:.3f}; identical {same}", flush=True)
    print(f"world-model env with LPIPS, {args.num_envs} envs, {args.wm_dtype} autocast, {torch.get_num_threads()} torch "
          f"thread(s), this machine: bf16 / fp32 KV cache median {np.median(ratios):.3f}, range "
          f"{min(ratios):.3f}-{max(ratios):.3f} over {args.rounds} alternating round(s)")


if __name__ == "__main__":
    main()
