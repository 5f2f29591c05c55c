"""World-model rollout speed vs the simulator, in one run (random weights: speed does not depend on them).

Prints, for the toy and small action-WM sizes at batch 1, 16 and 64:
  - env steps/s of the WM step alone, + tokenizer decoding, + reward (done head, already in the
    step, plus an LPIPS dense term of the decoded third view against a goal whose LPIPS features
    are computed once per env);
  - the per-step cost at step 15 over step 1 (the temporal KV cache grows; target <= 1.3);
  - achieved matmul FLOP/s of the WM step (counted analytically, ``matmul_flops_per_step``) as a
    fraction of this machine's 1-thread fp32 1024^3 matmul rate measured in the same run
    (target >= 50%), and of the rate of a linear layer of the model's own shape;
then ManiSkill PickCube-v1 env steps/s at 64x64 RGB (low-poly Panda unless --stock) and the ratio.

What is compared: one world-model step is ``frame_skip`` control steps of the simulator (train_wm's
``frame_skip``, default 4; stages/common/frame_skip.py), and the RL policy acts once per step in
both environments (the simulator env repeats the action, stages/common/sim_env.py). So the ratio is
given per policy step (the same 0.2 s of robot time in both): WM steps/s over simulator control
steps/s divided by frame_skip; the per-control-step ratio is printed too.

    .venv/bin/python benchmarks/wm_rollout.py            # ~3-4 minutes on 2 cores
    .venv/bin/python benchmarks/wm_rollout.py --no-sim   # world model only
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages.train_wm import Config  # noqa: E402
from stages.train_wm.model import WMSpec, WorldModelNet, matmul_flops_per_step  # noqa: E402
from stages.train_wm.rollout import WorldModel  # noqa: E402

# the toy profile's train_wm overrides (as given to pipeline.yaml); small = Config defaults
TOY = dict(dim=32, depth=2, heads=2, head_depth=1, window=4, control_tokens=2)
HORIZON = 16  # steps per measured rollout (steps 0..15)


def matmul_rate(n: int = 1024, reps: int = 20) -> float:
    """Best-of-3 fp32 FLOP/s of an n x n x n matmul on the current thread count."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    for _ in range(3):
        a @ b
    best = 0.0
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(reps):
            a @ b
        best = max(best, 2 * n**3 * reps / (time.perf_counter() - t))
    return best


def linear_rate(rows: int, d_in: int, d_out: int, reps: int = 30) -> float:
    """Best-of-3 FLOP/s of a (rows, d_in) x (d_in, d_out) linear layer (the model's typical shape)."""
    lin, x = torch.nn.Linear(d_in, d_out), torch.randn(rows, d_in)
    with torch.no_grad():
        for _ in range(3):
            lin(x)
        best = 0.0
        for _ in range(3):
            t = time.perf_counter()
            for _ in range(reps):
                lin(x)
            best = max(best, 2 * rows * d_in * d_out * reps / (time.perf_counter() - t))
    return best


def make_tokenizer():
    """A random-weight tokenizer of the tokenize stage's default (small) architecture: 64 px, 10 bits, 8x8."""
    from stages.tokenize.model import ModelSpec, TokenizerNet
    from stages.tokenize.tokenizer import Tokenizer

    return Tokenizer(TokenizerNet(ModelSpec()))


@torch.no_grad()
def bench_size(name: str, spec: WMSpec, tok, lp, batch: int, repeats: int, decode_steps: int) -> dict:
    wm = WorldModel(WorldModelNet(spec), decode_steps=decode_steps)
    roll = wm.rollout(batch)
    h, w = spec.grid
    tokens0 = torch.randint(0, spec.vocab_size, (batch, h, w))
    goal = lp.features(tok.decode(torch.randint(0, spec.vocab_size, (batch, h, w)))[0] * 2 - 1)  # once per env
    t_wm = [[] for _ in range(HORIZON)]
    t_dec, t_rew, flops, wm_total = [], [], 0.0, 0.0
    for r in range(repeats + 1):  # the first repeat warms up
        roll.reset(tokens0)
        for i in range(HORIZON):
            a = torch.rand(batch, 7) * 2 - 1
            t0 = time.perf_counter()
            out = roll.step(a)
            t1 = time.perf_counter()
            third, _ = tok.decode(out.tokens)
            t2 = time.perf_counter()
            dist = lp.distance_from_features(lp.features(third * 2 - 1), goal)
            reward = (out.done_prob >= 0.5).float() + (1 - dist)  # sparse + dense similarity
            t3 = time.perf_counter()
            assert torch.isfinite(reward).all()
            if r:
                t_wm[i].append(t1 - t0)
                t_dec.append(t2 - t1)
                t_rew.append(t3 - t2)
                flops += matmul_flops_per_step(spec, batch, min(i + 1, spec.window), decode_steps)
                wm_total += t1 - t0
    wm_step = wm_total / (repeats * HORIZON)
    dec, rew = statistics.mean(t_dec), statistics.mean(t_rew)
    return {"size": name, "batch": batch, "wm_sps": batch / wm_step, "dec_sps": batch / (wm_step + dec),
            "full_sps": batch / (wm_step + dec + rew), "ratio_15_1": statistics.median(t_wm[15]) / statistics.median(t_wm[1]),
            "gflops": flops / wm_total / 1e9, "ms_wm": wm_step * 1e3, "ms_dec": dec * 1e3, "ms_rew": rew * 1e3}


def bench_sim(stock: bool, steps: int) -> tuple[float, str]:
    """ManiSkill PickCube-v1 env steps/s, 64x64 RGB, CPU physics and rendering, random actions."""
    from stages.common.vulkan import ensure_vulkan

    ensure_vulkan()
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401

    from stages.collect.robot_mesh import use_robot_mesh

    mesh = "stock" if stock else "lowpoly"
    use_robot_mesh(mesh)
    env = gym.make("PickCube-v1", obs_mode="rgb", sim_backend="physx_cpu", render_backend="cpu",
                   sensor_configs=dict(width=64, height=64))
    env.reset(seed=0)
    for _ in range(10):
        env.step(env.action_space.sample())
    t = time.perf_counter()
    for i in range(steps):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if bool(term) or bool(trunc):
            env.reset(seed=i)
    sps = steps / (time.perf_counter() - t)
    env.close()
    return sps, mesh


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="measured 16-step rollouts per (size, batch)")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64])
    ap.add_argument("--decode-steps", type=int, default=Config().decode_steps)
    ap.add_argument("--no-sim", action="store_true", help="skip the ManiSkill measurement")
    ap.add_argument("--stock", action="store_true", help="stock Panda meshes instead of the low-poly ones")
    ap.add_argument("--sim-steps", type=int, default=200)
    ap.add_argument("--frame-skip", type=int, default=Config().frame_skip,
                    help="control steps per world-model step (train_wm.frame_skip)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    from stages.common.lpips import get_lpips

    tok, lp = make_tokenizer(), get_lpips("cpu")
    vocab, grid = tok.vocab_size, tok.grid
    small = Config()
    sizes: dict = {"toy": WMSpec(kind="action", vocab_size=vocab, grid=grid, **TOY),
             "small": WMSpec(kind="action", vocab_size=vocab, grid=grid, dim=small.dim, depth=small.depth,
                             heads=small.heads, head_depth=small.head_depth, mlp_ratio=small.mlp_ratio,
                             window=small.window, control_tokens=small.control_tokens, frame_skip=small.frame_skip)}
    mm = matmul_rate()
    best: dict[str, dict] = {}
    print(f"threads=1  fp32 matmul 1024^3: {mm / 1e9:.1f} GFLOP/s   decode_steps={args.decode_steps}  "
          f"tokenizer 64px {grid[0]}x{grid[1]} vocab {vocab}")
    for name, spec in sizes.items():
        params = sum(p.numel() for p in WorldModelNet(spec).parameters())
        lin = linear_rate(64 * spec.tokens, spec.dim, 3 * spec.dim)
        print(f"\n{name}: dim {spec.dim} depth {spec.depth} head_depth {spec.head_depth} window {spec.window} "
              f"({params / 1e6:.2f} M params); linear ({64 * spec.tokens}x{spec.dim}x{3 * spec.dim}) "
              f"{lin / 1e9:.1f} GFLOP/s")
        print(f"{'batch':>6} {'WM only':>9} {'+decode':>9} {'+reward':>9}   {'ms WM/dec/rew per step':>24}"
              f" {'step15/step1':>12} {'GFLOP/s':>8} {'%matmul':>8} {'%linear':>8}")
        for b in args.batches:
            r = bench_size(name, spec, tok, lp, b, args.repeats, args.decode_steps)
            print(f"{b:>6} {r['wm_sps']:>9.0f} {r['dec_sps']:>9.0f} {r['full_sps']:>9.0f}   "
                  f"{r['ms_wm']:>8.1f} /{r['ms_dec']:>6.1f} /{r['ms_rew']:>6.1f} {r['ratio_15_1']:>12.2f} "
                  f"{r['gflops']:>8.1f} {r['gflops'] * 1e9 / mm:>8.0%} {r['gflops'] * 1e9 / lin:>8.0%}")
            if b == max(args.batches):
                best[name] = r
    if not args.no_sim:
        sps, mesh = bench_sim(args.stock, args.sim_steps)
        k = args.frame_skip
        print(f"\nManiSkill PickCube-v1, 64x64 RGB, physx_cpu + cpu render, {mesh} Panda: {sps:.1f} control steps/s "
              f"= {sps / k:.1f} policy steps/s at frame_skip {k}")
        for name in ("toy", "small"):
            r = best[name]
            print(f"{name} WM at batch {r['batch']} / simulator, per policy step (frame_skip {k}): "
                  f"WM only {r['wm_sps'] / (sps / k):.1f}x, +decode {r['dec_sps'] / (sps / k):.1f}x, "
                  f"+decode+reward {r['full_sps'] / (sps / k):.1f}x   "
                  f"(per control step: {r['wm_sps'] / sps:.1f}x / {r['dec_sps'] / sps:.1f}x / {r['full_sps'] / sps:.1f}x)")


if __name__ == "__main__":
    main()
