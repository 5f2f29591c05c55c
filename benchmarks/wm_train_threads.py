"""World-model training step time by torch thread count, measured in one run (random weights and
random clips: the step's cost does not depend on their values).

The step is ``stages.train_wm.train.train_world_model``'s (train_wm's and wm_play's fine-tune: the
same losses, AdamW, batch of ``batch_size`` clips of ``window`` steps), for the action world model at
the ``small`` profile's size (train_wm's ``Config`` defaults, two 8 x 8 token grids per frame). Each
thread count runs ``--repeats`` times, alternating, so a slow spell of a noisy machine falls on both;
the ratio printed is the one-thread mean over the other count's.

    .venv/bin/python benchmarks/wm_train_threads.py [--threads 1 2] [--steps 20] [--repeats 2]
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

from stages.train_wm import Config, model_spec  # noqa: E402
from stages.train_wm.data import ClipSampler, Episode  # noqa: E402
from stages.train_wm.model import WorldModelNet  # noqa: E402
from stages.train_wm.train import train_world_model  # noqa: E402

TOKENS = 2 * 8 * 8  # two views, one 8 x 8 grid each, stacked to (16, 8) (the small profile's tokenizer)
VOCAB = 2**10  # tokenizer bits 10


def random_episodes(n: int, length: int, seed: int = 0) -> list[Episode]:
    """``n`` episodes of ``length`` world-model steps with random tokens, actions and proprioception."""
    rng = np.random.default_rng(seed)
    done = (np.arange(length + 1) >= length - 3).astype(np.float32)  # the last frames succeed
    return [Episode(f"e{i}", "push the cube", "ind", rng.integers(0, VOCAB, (length + 1, TOKENS)),
                    rng.uniform(-1, 1, (length, 7)).astype(np.float32), done,
                    rng.normal(size=(length + 1, 10)).astype(np.float32)) for i in range(n)]


def seconds_per_step(threads: int, steps: int, episodes: list[Episode], c: Config) -> float:
    """Mean seconds per training step on ``threads`` torch threads (after one untimed warm-up step)."""
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    net = WorldModelNet(model_spec(c, "action", VOCAB, (16, 8)))  # train_wm's own architecture for this config
    net.set_action_stats(torch.from_numpy(np.concatenate([e.actions for e in episodes])))
    text = {"push the cube": np.full(384, 384**-0.5, np.float32)}
    kw = dict(batch_size=c.batch_size, lr=c.lr, weight_decay=c.weight_decay, done_weight=c.done_weight,
              done_kind=c.done_loss, seed=0, device="cpu", changed_weight=c.changed_weight,
              done_balance=c.done_balance, context_noise=c.context_noise, self_context=c.self_context)
    train_world_model(net, ClipSampler(episodes, c.window, text, 0), steps=1, **kw)
    t = time.perf_counter()
    train_world_model(net, ClipSampler(episodes, c.window, text, 1), steps=steps, **kw)
    return (time.perf_counter() - t) / steps


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--steps", type=int, default=20, help="timed steps per measurement")
    ap.add_argument("--repeats", type=int, default=2, help="measurements per thread count, alternating")
    args = ap.parse_args()
    c = Config()
    episodes = random_episodes(40, 19)
    times: dict[int, list[float]] = {t: [] for t in args.threads}
    for _ in range(args.repeats):
        for t in args.threads:
            times[t].append(seconds_per_step(t, args.steps, episodes, c))
    print(f"world-model training step, small-profile action WM (dim {c.dim}, depth {c.depth}, {TOKENS} tokens/frame, "
          f"batch {c.batch_size} clips x {c.window} steps), {args.steps} steps x {args.repeats} alternating repeats, "
          "this machine:")
    base = statistics.mean(times[args.threads[0]])
    for t in args.threads:
        mean = statistics.mean(times[t])
        runs = " / ".join(f"{x:.3f}" for x in times[t])
        print(f"  {t} thread(s): {runs} s/step (mean {mean:.3f}); ratio {args.threads[0]} thread(s) / {t}: {base / mean:.2f}")


if __name__ == "__main__":
    main()
