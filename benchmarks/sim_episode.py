"""What an evaluation episode in ManiSkill costs, measured in one run, five ways:

  fresh   the old evaluate job: build the simulator env, run one episode, close it (each job), the
          process's renderer freed with it, so the next env's first picture regenerates it (SAPIEN's
          BRDF lookup table, docs/collect.md)
  held    the same with the renderer held for the process's life, as the simulator env now does
          (stages/common/sim_env.py:keep_renderer): what a simulator rebuilt in a process costs
  kept    the current job: one env per worker process kept between jobs (a new scene each episode,
          so building the scene is included; stages/evaluate/episodes.py:_sim_for)
  render  like ``kept`` but rendering both cameras at every control step (``keep_frames``), as the
          env did before it skipped the unobserved control steps of a policy step
  cached  like ``kept`` but in scenes the env has built before (a ``cache_size`` that covers them):
          what the rl stage's simulator envs (2 of their 48 scenes kept) would save by keeping all

Each episode: ``--steps`` policy steps of ``frame_skip`` control steps (random actions: speed does
not depend on the policy), the small tokenizer's architecture (random weights) as the observation.
Scenes are the default catalog's IND scenes, one per episode, task push. Prints seconds per episode
and the ratios fresh/held, held/kept, render/kept and kept/cached.

    .venv/bin/python benchmarks/sim_episode.py [--episodes 3] [--steps 75]
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


def episode(env, spec, seed: int, steps: int, rng: np.random.Generator) -> None:
    env.reset(seed=seed, options={"spec": spec})
    for _ in range(steps):
        env.step(rng.uniform(-1, 1, 7).astype(np.float32))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=3, help="episodes per way")
    ap.add_argument("--steps", type=int, default=75, help="policy steps per episode (evaluate.max_steps)")
    ap.add_argument("--frame-skip", type=int, default=4, help="control steps per policy step (train_wm.frame_skip)")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from rl_throughput import tokenizer  # the small tokenizer architecture, random weights
    from stages.collect.sim import default_catalog
    from stages.sft.observation import ObservationFn
    from stages.common import sim_env
    from stages.common.sim_env import SimSpec, SimTaskEnv

    scenes = [s for s in default_catalog().values() if s.split == "ind"]
    specs = [SimSpec("push", s.to_dict()) for s in scenes]
    tok = tokenizer("cpu")
    obs_fn = ObservationFn(tok, {})
    rng = np.random.default_rng(0)

    def make(spec, **kw):
        return SimTaskEnv([spec], obs_fn, max_steps=args.steps, action_repeat=args.frame_skip, **kw)

    warm = make(specs[-1])  # pays the process's one-time start-up (imports, Vulkan) outside the timings
    episode(warm, specs[-1], 0, 1, rng)
    warm.close()
    del warm

    times: dict[str, list[float]] = {"fresh": [], "held": [], "kept": [], "render": [], "cached": []}
    for i in range(args.episodes):  # held: a new env per episode, closed after it, the renderer held
        t = time.perf_counter()
        env = make(specs[i])
        episode(env, specs[i], 500 + i, args.steps, rng)
        env.close()
        del env
        times["held"].append(time.perf_counter() - t)
    for i in range(-1, args.episodes):  # fresh: the same, the renderer freed with each env (i = -1: untimed,
        t = time.perf_counter()         # it frees the renderer the loop above held)
        env = make(specs[max(i, 0)])
        episode(env, specs[max(i, 0)], 100 + i, args.steps if i >= 0 else 1, rng)
        sim_env._KEPT_RENDERERS.clear()  # as before keep_renderer: closing the last env frees the renderer
        env.close()
        del env
        if i >= 0:
            times["fresh"].append(time.perf_counter() - t)
    kept = make(specs[0])
    episode(kept, specs[0], 1, 1, rng)  # the fresh loop closed the process's last env: pay that once, untimed
    for way, offset in (("kept", 0), ("render", args.episodes)):
        kept.keep_frames = way == "render"
        for i in range(args.episodes):
            spec = specs[(offset + i + 1) % len(specs)]  # a scene this env has not built yet
            t = time.perf_counter()
            episode(kept, spec, 200 + offset + i, args.steps, rng)
            times[way].append(time.perf_counter() - t)
    kept.close()
    cached = make(specs[0], cache_size=len(specs))
    for i in range(args.episodes):  # build each scene once, untimed
        episode(cached, specs[i], 300 + i, 1, rng)
    for i in range(args.episodes):
        t = time.perf_counter()
        episode(cached, specs[i], 400 + i, args.steps, rng)
        times["cached"].append(time.perf_counter() - t)
    cached.close()

    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"episode = {args.steps} policy steps x {args.frame_skip} control steps, push, 64x64, low-poly Panda")
    for k, v in times.items():
        print(f"  {k:7s} median {med[k]:6.2f} s/episode  ({', '.join(f'{x:.2f}' for x in v)})")
    print(f"ratio fresh/held  {med['fresh'] / med['held']:.2f}x  (holding the renderer when a simulator is rebuilt)")
    print(f"ratio held/kept   {med['held'] / med['kept']:.2f}x  (keeping a worker's simulator between jobs)")
    print(f"ratio render/kept {med['render'] / med['kept']:.2f}x  (rendering only the observed control step)")
    print(f"ratio kept/cached {med['kept'] / med['cached']:.2f}x  (keeping every scene built)")


if __name__ == "__main__":
    main()
