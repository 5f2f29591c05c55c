"""A sweep wave's torch threads, measured in one run: what two rl nodes side by side get done.

The local executor runs a sweep's nodes of one stage several at once (``--jobs``), each in its own
process; every rl, sft and wm_play node then sets torch to its config's ``threads`` (in the key,
default 2). On a 2-core machine a wave of two rl nodes at the default count runs four torch
threads on two cores. This benchmark times that against the alternatives, all in one run:

- ``1 x 2``: one process on 2 threads (a single run, or a sweep at ``--jobs 1``);
- ``2 x 1``: two processes at once, 1 thread each;
- ``2 x 2``: two processes at once, 2 threads each (a ``--jobs 2`` wave at the defaults);
- ``1 x 2 passive`` and ``2 x 2 passive``: the same with ``OMP_WAIT_POLICY=PASSIVE`` in the
  processes' environment (torch's OpenMP threads then sleep at the end of a parallel region instead
  of spinning, which only changes scheduling, not a result).

Each process is PPO in the world-model env as ``benchmarks/rl_throughput.py`` builds it (the
small profile's action WM with random weights, ``--num-envs`` batched envs, the ``wm`` reward with
LPIPS to a goal, so every step decodes its frame; the SFT-shaped policy). The processes build and
warm up first (one rollout and update each) and start their timed ``--steps`` together. Printed:
each layout's summed env steps/s over its processes and the ratio to ``1 x 2``; a ratio below 1
means the wave gets less done than running its nodes one after another. ``--rounds`` repeats the
layouts in turn, so a slow spell of a noisy machine falls on all of them.

    .venv/bin/python benchmarks/wave_threads.py [--steps 1024] [--num-envs 16] [--rounds 2] [--layouts 1x2,2x2,2x2p]

``--layouts`` picks layouts by name (``PxT``: P processes of T threads; a trailing ``p``: passive);
the first is the one the others are compared with.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYOUTS = "1x2,2x1,2x2,1x2p,2x2p"  # the default layouts, the first the base of the ratios


def worker(threads: int, steps: int, num_envs: int) -> None:
    """Build and warm up PPO in the world-model env, say ``ready``, wait for ``go`` on stdin, then
    print ``{"rate": env steps/s}`` of ``steps`` timed steps."""
    import torch

    torch.set_num_threads(threads)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    sys.path.insert(0, str(ROOT))
    from rl_throughput import Setup, ppo_cfg, sft_policy

    from stages.rl.ppo import make_ppo

    env = Setup("cpu").wm_env(0.02, num_envs, "auto")
    policy, info = sft_policy(env.observation_space)
    model = make_ppo(env, ppo_cfg(num_envs), policy, info, device="cpu")
    model.learn(total_timesteps=64 * num_envs)  # warm-up: one rollout + update
    print("ready", flush=True)
    sys.stdin.readline()
    t, start = time.perf_counter(), model.num_timesteps
    model.learn(total_timesteps=steps, reset_num_timesteps=False)
    print(json.dumps({"rate": (model.num_timesteps - start) / (time.perf_counter() - t)}), flush=True)


def wave(processes: int, threads: int, wait_policy: str, steps: int, num_envs: int) -> float:
    """Summed env steps/s of ``processes`` workers timed together, each on ``threads`` threads."""
    cmd = [sys.executable, __file__, "--worker", "--threads", str(threads), "--steps", str(steps),
           "--num-envs", str(num_envs)]
    env = dict(os.environ)
    if wait_policy:
        env["OMP_WAIT_POLICY"] = wait_policy
    procs = [subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT, env=env)
             for _ in range(processes)]
    try:
        for p in procs:  # every process built and warmed up before any timed step
            line = p.stdout.readline().strip()
            if line != "ready":
                raise RuntimeError(f"a worker ({threads} threads) failed before its timed steps: {line!r}")
        for p in procs:
            p.stdin.write("go\n")
            p.stdin.flush()
        rates = [json.loads(p.stdout.readline())["rate"] for p in procs]
    finally:
        for p in procs:
            p.wait()
    return sum(rates)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=1024, help="timed PPO env steps per process")
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=2, help="repeat the layouts in turn this many times")
    ap.add_argument("--layouts", default=LAYOUTS, help=f"comma-separated layouts (default {LAYOUTS})")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.threads, args.steps, args.num_envs)
        return
    if args.rounds < 1 or args.steps < 1:
        ap.error("--rounds and --steps must be >= 1")
    try:
        layouts = [parse_layout(text) for text in args.layouts.split(",")]
    except ValueError as e:
        ap.error(str(e))
    rates: dict[tuple, list[float]] = {layout: [] for layout in layouts}
    for r in range(args.rounds):
        for layout in layouts:
            rates[layout].append(wave(*layout, args.steps, args.num_envs))
        print(f"  round {r + 1}/{args.rounds}: " + ", ".join(
            f"{name(layout)} {rates[layout][-1]:.1f}" for layout in layouts) + " env steps/s (summed)", flush=True)
    base = statistics.median(rates[layouts[0]])
    print(f"PPO in the world-model env, {args.num_envs} envs per process, {args.steps} timed steps each, "
          f"{os.cpu_count()} CPUs, OMP_WAIT_POLICY here {os.environ.get('OMP_WAIT_POLICY', 'unset')}, "
          f"median of {args.rounds} round(s):")
    for layout in layouts:
        m = statistics.median(rates[layout])
        print(f"  {name(layout)}: {m:.1f} env steps/s summed, {m / base:.2f}x {name(layouts[0])}")


def parse_layout(text: str) -> tuple[int, int, str]:
    """``"2x2p"`` -> (2 processes, 2 threads, "PASSIVE"); ``"1x2"`` -> (1, 2, "")."""
    body, policy = (text[:-1], "PASSIVE") if text.endswith("p") else (text, "")
    procs, sep, threads = body.partition("x")
    if not (sep and procs.isdigit() and threads.isdigit() and int(procs) >= 1 and int(threads) >= 1):
        raise ValueError(f"--layouts: {text!r} is not PxT or PxTp (P processes, T threads, p: passive wait)")
    return int(procs), int(threads), policy


def name(layout: tuple) -> str:
    """``2 x 2`` (processes x threads), with `` passive`` when the layout sets OMP_WAIT_POLICY=PASSIVE."""
    p, t, policy = layout
    return f"{p} x {t}" + (f" {policy.lower()}" if policy else "")


if __name__ == "__main__":
    main()
