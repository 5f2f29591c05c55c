"""PPO throughput, measured in one run: env steps/s (updates included) inside the world-model env
vs inside ManiSkill, with the same observation (64x64 views -> tokenizer latent + instruction).

World-model side: the action WM at the ``small`` profile's size (random weights: speed does not
depend on them), ``num_envs`` batched envs, reward = the ``wm`` module (done head + LPIPS to a
cached goal, so every step decodes its frame), and once more with the sparse term only (beta 0:
the env decodes no frame); the world model's step, decoding and LPIPS convolutions in ``--wm-dtype``
(as the rl stage's ``wm_dtype``, default auto: bf16 where this CPU runs it fast), the decoder and
LPIPS network in the memory layout ``stages.common.precision.conv_layout`` times faster here (printed). The simulator side's observation
encoding stays fp32 in every case (the policy was trained on fp32 tokens). Simulator side: the push task with the low-poly
Panda, ``sim_envs`` envs in a DummyVecEnv, reward = the task's rule reward; every frame goes
through the same tokenizer. Both use the same PPO settings and policy. An env step is a policy step
in both: one world-model frame = ``frame_skip`` control steps, which the simulator env runs by
repeating the action (stages/common/sim_env.py), so both advance the same robot time per step.

    .venv/bin/python benchmarks/rl_throughput.py [--wm-steps 2048] [--sim-steps 256] [--num-envs 16] [--threads N] [--rounds 3] [--device cuda]

``--rounds`` repeats the three measurements in turn (world model with LPIPS, sparse only,
ManiSkill) and prints each round's ratio and their median: on a 2-core CPU the ManiSkill side alone
moved between 36 and 53 steps/s from one run to the next (docs/rl.md, "Throughput"), so one round's
ratio carries that spread and the rounds show it within one run.

On a CPU both envs run on ``--threads`` torch threads, by default the rl stage's ``threads`` (what the
stage runs with).

The instruction's embedding is a fixed random unit vector (no text-encoder weights needed).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def tokenizer(device: str):
    from stages.tokenize import Config as TokConfig
    from stages.tokenize.model import ModelSpec, TokenizerNet
    from stages.tokenize.tokenizer import Tokenizer

    c = TokConfig()
    torch.manual_seed(0)
    return Tokenizer(TokenizerNet(c.spec()), device)  # the small profile's architecture (one grid per view)


def instruction_embedding(instruction: str) -> dict[str, np.ndarray]:
    """A fixed random unit vector as the instruction's embedding: like every weight here, its value
    does not change the speed, and the benchmark then needs no text-encoder weights."""
    from stages.sft.observation import TEXT_DIM

    v = np.random.default_rng(0).standard_normal(TEXT_DIM).astype(np.float32)
    return {instruction: v / np.linalg.norm(v)}


def action_wm(tok, device: str):
    from stages.train_wm import Config as WMConfig
    from stages.train_wm.model import WMSpec, WorldModelNet
    from stages.train_wm.proprio import ProprioHead
    from stages.train_wm.rollout import WorldModel

    c = WMConfig()
    torch.manual_seed(0)
    net = WorldModelNet(WMSpec(kind="action", vocab_size=tok.vocab_size, grid=tok.grid, dim=c.dim, depth=c.depth,
                               heads=c.heads, head_depth=c.head_depth, mlp_ratio=c.mlp_ratio, window=c.window,
                               control_tokens=c.control_tokens, frame_skip=c.frame_skip))
    net.set_action_stats(torch.rand(256, 7) * 2 - 1)
    return WorldModel(net.to(device).eval(), decode_steps=c.decode_steps,
                      proprio_head=ProprioHead(tok.bits, tok.grid).to(device).eval())


def ppo_cfg(num_envs: int):
    from stages.rl import Config

    c = Config()
    return SimpleNamespace(**{**c.model_dump(), "n_steps": 64, "batch_size": min(256, 64 * num_envs)})


def sft_policy(space):
    """An untrained policy of the sft stage's architecture and its policy.json facts."""
    from stages.sft import Config as SFTConfig
    from stages.sft.policy import make_policy, policy_kwargs

    c = SFTConfig()
    kwargs = policy_kwargs([0.0] * 7, [0.1] * 6 + [1.0], features_dim=c.features_dim, net_arch=c.net_arch)
    info = {"policy_kwargs": {k: v for k, v in kwargs.items() if k != "features_extractor_class"}}
    return make_policy(space, kwargs), info


def timed_learn(env, steps: int, num_envs: int, device: str) -> float:
    from stages.rl.ppo import make_ppo

    policy, info = sft_policy(env.observation_space)
    model = make_ppo(env, ppo_cfg(num_envs), policy, info, device=device)
    model.learn(total_timesteps=64 * num_envs)  # warm-up: one rollout + update
    t = time.perf_counter()
    model.learn(total_timesteps=steps, reset_num_timesteps=False)
    return (model.num_timesteps - 64 * num_envs) / (time.perf_counter() - t)


def stage_threads() -> int:
    """The torch threads the rl stage runs with on a CPU: its config's default ``threads``."""
    from stages.rl import Config

    return Config().threads


class Setup:
    """What both environments share: the tokenizer, the observation function, a real push scene's
    first frame (rendered once) as every world-model episode's start and goal, the action WM."""

    def __init__(self, device: str):
        from stages.collect.sim import default_catalog
        from stages.common.sim_env import SimSpec, SimTaskEnv
        from stages.sft.observation import ObservationFn

        self.device = device
        self.tok = tokenizer(device)
        scene = next(s for s in default_catalog().values() if s.split == "ind")
        self.spec = SimSpec("push", scene.to_dict(), instruction="push the object to the goal")  # any text: see instruction_embedding
        self.obs_fn = ObservationFn(self.tok, instruction_embedding(self.spec.instruction))
        probe = SimTaskEnv([self.spec], self.obs_fn, max_steps=50, keep_frames=True)
        first, _ = probe.reset(seed=0)
        self.instruction, self.proprio = probe.instruction, first["proprio"]
        third, wrist = probe.frames[0]
        probe.close()
        self.tokens = self.tok.encode(third[None], wrist[None]).cpu().numpy()[0]  # (h, w)
        self.wm = action_wm(self.tok, device)
        self.goal = self.tok.decode(torch.as_tensor(self.tokens[None], device=device))  # (third, wrist), each (1, 3, S, S)

    def wm_env(self, beta: float, num_envs: int, wm_dtype: str, tok=None):
        """The world-model env with the ``wm`` reward (beta 0: sparse only, no frame decoded), on ``tok``
        (default the shared tokenizer)."""
        from stages.rl.rewards import GoalDistance, WMReward
        from stages.rl.wm_env import Start, WorldModelVecEnv

        reward = WMReward(GoalDistance(*self.goal, self.device, dtype=wm_dtype), alpha=2.0, beta=beta, theta_sps=0.5,
                          num_envs=num_envs)
        return WorldModelVecEnv(self.wm, tok or self.tok, self.obs_fn, reward,
                                [Start(0, self.instruction, self.tokens, self.proprio)], num_envs=num_envs,
                                max_steps=50, theta_done=0.999, seed=0, device=self.device, dtype=wm_dtype)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--wm-steps", type=int, default=2048)
    ap.add_argument("--sim-steps", type=int, default=256)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--sim-envs", type=int, default=2)
    ap.add_argument("--wm-dtype", choices=["fp32", "bf16", "auto"], default="auto",
                    help="the world-model env's step, decoding and LPIPS (the rl stage's wm_dtype; default as there)")
    ap.add_argument("--device", default="cpu",
                    help="torch device of the tokenizer, world model, LPIPS and PPO in both envs, as the rl stage's "
                         "--device (the simulator itself always runs on the CPU)")
    ap.add_argument("--rounds", type=int, default=3,
                    help="measure each env this many times, in turn, and print every round's ratio and the median")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads on a CPU, in both envs (default: the rl stage's `threads`, what it runs "
                         "with)")
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds must be >= 1, got {args.rounds}")
    if args.threads is None:
        args.threads = stage_threads()
    if args.device == "cpu":
        torch.set_num_threads(args.threads)
    dev = args.device
    os.environ.setdefault("HF_HUB_OFFLINE", "1")

    from stable_baselines3.common.vec_env import DummyVecEnv

    from stages.common.precision import layout_of
    from stages.common.sim_env import SimTaskEnv

    setup = Setup(dev)
    tok, obs_fn, spec, wm = setup.tok, setup.obs_fn, setup.spec, setup.wm

    def wm_env(beta: float):
        return setup.wm_env(beta, args.num_envs, args.wm_dtype)

    k = wm.spec.frame_skip
    dense_env, sparse_env = wm_env(0.02), wm_env(0.0)  # wm reward with LPIPS (every frame decoded) / sparse only
    sim_env = DummyVecEnv([lambda i=i: SimTaskEnv([spec], obs_fn, max_steps=50, seed=i,
                                                  action_repeat=k) for i in range(args.sim_envs)])
    rounds = []  # (with LPIPS, sparse only, ManiSkill) steps/s per round
    for r in range(args.rounds):
        rates = (timed_learn(dense_env, args.wm_steps, args.num_envs, dev),
                 timed_learn(sparse_env, args.wm_steps, args.num_envs, dev),
                 timed_learn(sim_env, args.sim_steps, args.sim_envs, dev))
        rounds.append(rates)
        print(f"  round {r + 1}/{args.rounds}: world model with LPIPS {rates[0]:.1f}, sparse only {rates[1]:.1f}, "
              f"ManiSkill {rates[2]:.1f} steps/s: ratio {rates[0] / rates[2]:.2f} (sparse only {rates[1] / rates[2]:.2f})",
              flush=True)
    sim_env.close()

    wm_rate, sparse_rate, sim_rate = (float(np.median([x[i] for x in rounds])) for i in range(3))
    ratio = [x[0] / x[2] for x in rounds]
    ratio_sparse = [x[1] / x[2] for x in rounds]
    where = f"{torch.get_num_threads()} torch thread(s)" if dev == "cpu" else f"device {dev} ({torch.cuda.get_device_name(dev)})"
    print(f"PPO env (= policy) steps/s, updates included (one run, {where}, this machine, median of "
          f"{args.rounds} round(s)); one step = {k} control steps in both envs")
    print(f"  world-model env: {args.num_envs} batched envs, small-profile action WM "
          f"(dim {wm.spec.dim}, depth {wm.spec.depth}, {wm.spec.tokens} tokens/frame, {wm.decode_steps} decoding passes, "
          f"{dense_env.dtype} (--wm-dtype {args.wm_dtype})), "
          f"wm reward with LPIPS: {wm_rate:.1f} (layouts timed here: decoder {layout_of(tok.net.decoder)}, "
          f"LPIPS {layout_of(dense_env.reward.distance.net)})")
    print(f"  world-model env, sparse reward only (no frame decoded): {sparse_rate:.1f}")
    print(f"  ManiSkill env:   {args.sim_envs} envs (push, low-poly Panda, 64x64 x 2 views, tokenizer obs), rule reward: {sim_rate:.1f} ({sim_rate * k:.1f} control steps/s)")
    print(f"  ratio world model / ManiSkill: median {np.median(ratio):.2f} over the rounds, range {min(ratio):.2f}-{max(ratio):.2f} "
          f"(sparse only: median {np.median(ratio_sparse):.2f}, range {min(ratio_sparse):.2f}-{max(ratio_sparse):.2f})")


if __name__ == "__main__":
    main()
