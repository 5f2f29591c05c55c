"""bf16 autocast vs fp32 on this machine, measured in one run: speed of the pieces a world-model
PPO step is made of, and (given trained artifacts) what bf16 does to the action world model's
open-loop predictions.

Speed (random weights at the ``small`` profile's sizes, 1 torch thread, ``--envs`` batched envs):
one linear layer, a world-model rollout step, a tokenizer decode (also with the decoder
channels-last, as the rl stage runs it in bf16), a tokenizer encode, LPIPS features (also
channels-last), and a world-model training step (8 clips). Fidelity (``--collect/--tokenize/--train-wm``): open-loop
rollouts from held-out IND and OOD frames under the recorded actions, in fp32 and in bf16; token
agreement between the two, each one's token accuracy against the real frames, and the largest
done-probability difference, at horizons 1, 5 and 15; and the dense reward's LPIPS distance
(frames to their episode's last frame) in bf16 against fp32.

    PYTHONPATH=. .venv/bin/python benchmarks/wm_precision.py [--collect C --tokenize T --train-wm W]
"""
from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.rl_throughput import action_wm, tokenizer  # noqa: E402
from stages.common.lpips import get_lpips  # noqa: E402
from stages.common.precision import autocast, conv_layout, cpu_bf16_speedup  # noqa: E402


def timed(fn, reps: int) -> float:
    """Best-of-3 mean milliseconds per call of ``fn`` over ``reps`` calls (after one warm-up call)."""
    fn()
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(reps):
            fn()
        best = min(best, (time.perf_counter() - t) / reps)
    return 1000 * best


def both(name: str, fn, reps: int) -> None:
    fp32 = timed(fn, reps)
    with autocast("cpu", "bf16"):
        bf16 = timed(fn, reps)
    print(f"  {name:<42} fp32 {fp32:8.2f} ms   bf16 {bf16:8.2f} ms   ratio {fp32 / bf16:5.2f}x")


def speed(envs: int) -> None:
    from stages.train_wm.train import losses

    tok, lin = tokenizer("cpu"), torch.nn.Linear(128, 512)
    wm = action_wm(tok, "cpu")
    x = torch.randn(envs * wm.spec.tokens, 128)
    roll = wm.rollout(envs)
    h, w = wm.spec.grid
    frames = torch.randint(0, wm.spec.vocab_size, (envs, h, w))
    roll.reset(frames)
    acts = torch.zeros(envs, 7)
    images = torch.randint(0, 255, (envs, 64, 64, 3), dtype=torch.uint8)
    print(f"speed (1 thread, {envs} envs, small-profile sizes, random weights; measured bf16/fp32 matmul speed-up "
          f"{cpu_bf16_speedup():.2f}x):")
    with torch.no_grad():
        both(f"linear 128->512 on {len(x)} rows", lambda: lin(x), 20)
        both("world-model rollout step", lambda: roll.step(acts), 5)
        both("tokenizer decode (both views)", lambda: tok.decode(frames), 5)
        both("tokenizer encode (both views)", lambda: tok.encode(images, images), 5)
        fast = tokenizer("cpu")
        conv_layout(fast.net.decoder, "cpu", "bf16")
        both("tokenizer decode, decoder channels-last", lambda: fast.decode(frames), 5)
        lp = get_lpips("cpu")
        x = torch.rand(envs, 3, 64, 64) * 2 - 1
        both(f"LPIPS features ({envs} frames, one view)", lambda: lp.features(x), 5)
        lp_fast = conv_layout(copy.deepcopy(lp), "cpu", "bf16")
        both("LPIPS features, channels-last", lambda: lp_fast.features(x), 5)
    net = wm.net.train()
    gen = torch.Generator().manual_seed(0)
    n, t = wm.spec.tokens, wm.spec.window
    batch = {"tokens": torch.randint(0, wm.spec.vocab_size, (8, t + 1, n)), "valid": torch.ones(8, t),
             "actions": torch.randn(8, t, 7) * 0.1, "done": torch.zeros(8, t)}

    def train_step():
        out = losses(net, batch, gen, "bce", 4.0, True)
        (out["ce"] + out["done"]).backward()
        net.zero_grad(set_to_none=True)

    both("world-model training step (8 clips, fwd+bwd)", train_step, 2)
    net.eval()


def fidelity(collect: Path, tok_dir: Path, wm_dir: Path, per_split: int) -> None:
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.data import load_episodes
    from stages.train_wm.evaluate import rollout_starts, true_actions
    from stages.train_wm.rollout import load_world_model

    tok = load_tokenizer(tok_dir)
    wm = load_world_model(wm_dir, "action")
    split = json.loads((wm_dir / "split.json").read_text())
    eps = {e.episode_id: e for e in load_episodes(collect, tok_dir, frame_skip=wm.spec.frame_skip)}
    horizons, hmax = (1, 5, 15), 15
    print(f"fidelity: action world model {wm_dir.name[:12]}, open loop from real frames under recorded actions, "
          f"{per_split} episodes x 4 starts per split, greedy decoding ({wm.decode_steps} passes)")
    for name, ids in (("held-out IND", split["heldout"]), ("OOD", split["ood"])):
        rng = np.random.default_rng(0)
        chosen = [eps[i] for i in sorted(rng.choice(ids, size=min(per_split, len(ids)), replace=False))]
        starts = rollout_starts(chosen, hmax, 4, rng)
        acts = true_actions(chosen, starts, hmax)  # (K, H, 7)
        k = len(starts)
        real = torch.stack([torch.from_numpy(chosen[i].tokens[s + 1: s + 1 + hmax]) for i, s in starts])  # (K, H, N)
        runs = {}
        for mode in ("fp32", "bf16"):
            h, w = wm.spec.grid
            roll = wm.rollout(k)
            roll.reset(torch.stack([torch.from_numpy(chosen[i].tokens[s]) for i, s in starts]).view(k, h, w))
            toks, done = [], []
            with torch.no_grad(), autocast("cpu", mode):
                for t in range(hmax):
                    out = roll.step(acts[:, t])
                    toks.append(out.tokens.reshape(k, -1))
                    done.append(out.done_prob.float())
            runs[mode] = (torch.stack(toks, 1), torch.stack(done, 1))  # (K, H, N), (K, H)
        (a, da), (b, db) = runs["fp32"], runs["bf16"]
        cells = []
        for hz in horizons:
            agree = float((a[:, hz - 1] == b[:, hz - 1]).float().mean())
            acc32 = float((a[:, hz - 1] == real[:, hz - 1]).float().mean())
            acc16 = float((b[:, hz - 1] == real[:, hz - 1]).float().mean())
            cells.append(f"h{hz}: agree {agree:.3f}, acc fp32 {acc32:.3f} / bf16 {acc16:.3f}")
        print(f"  {name} ({k} starts): " + "; ".join(cells)
              + f"; max |done fp32 - bf16| {float((da - db).abs().max()):.3f}, "
                f"done >= 0.5 agree {float(((da >= 0.5) == (db >= 0.5)).float().mean()):.3f}")
        lpips_fidelity(tok, chosen)


def lpips_fidelity(tok, chosen: list) -> None:
    """The dense reward's LPIPS distance in bf16 vs fp32: each episode's frames to its last frame."""
    from stages.rl.rewards import GoalDistance

    third, wrist, goal_index, goals3, goalsw = [], [], [], [], []
    with torch.no_grad():
        for g, ep in enumerate(chosen):
            frames = torch.from_numpy(ep.tokens[:: max(1, len(ep.tokens) // 8)].astype(np.int64)).view(-1, *tok.grid)  # (~8, h, w)
            t3, tw = tok.decode(frames)
            third.append(t3)
            wrist.append(tw)
            goal_index += [g] * len(frames)
            l3, lw = tok.decode(torch.from_numpy(ep.tokens[-1:].astype(np.int64)).view(1, *tok.grid))
            goals3.append(l3)
            goalsw.append(lw)
    third, wrist, goal_index = torch.cat(third), torch.cat(wrist), np.asarray(goal_index)
    d = {m: GoalDistance(torch.cat(goals3), torch.cat(goalsw), dtype=m)(third, wrist, goal_index) for m in ("fp32", "bf16")}
    diff = np.abs(d["bf16"] - d["fp32"])
    ranks = [np.argsort(np.argsort(d[m])) for m in ("fp32", "bf16")]
    print(f"  LPIPS to the episode's last frame ({len(goal_index)} decoded frames, {len(chosen)} episodes): "
          f"mean {d['fp32'].mean():.4f}, |bf16 - fp32| mean {diff.mean():.5f} max {diff.max():.5f}, "
          f"Spearman {np.corrcoef(*ranks)[0, 1]:.4f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--envs", type=int, default=16)
    ap.add_argument("--collect", type=Path)
    ap.add_argument("--tokenize", type=Path)
    ap.add_argument("--train-wm", type=Path)
    ap.add_argument("--episodes", type=int, default=32, help="episodes per split for the fidelity check")
    args = ap.parse_args()
    torch.set_num_threads(1)
    speed(args.envs)
    given = [args.collect, args.tokenize, args.train_wm]
    if any(given):
        if not all(given):
            ap.error("the fidelity check needs --collect, --tokenize and --train-wm")
        fidelity(args.collect, args.tokenize, args.train_wm, args.episodes)


if __name__ == "__main__":
    main()
