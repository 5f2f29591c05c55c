"""Does the policy exploit the world model? Imagine, then replay the imagined actions in ManiSkill.

For each of N in-domain (task, scene) environments: reset the simulator (a new seed), tokenize its
first frame, roll the trained policy closed-loop inside the action world model from that frame
for up to ``--steps`` policy steps (recording its actions, clipped to the world model's action
range as the world model clips them, and the done head), then replay exactly those actions open loop in the simulator from the same initial state (each repeated
``frame_skip`` control steps, as in training). A world model the policy does not exploit says
"done" mostly where the simulator says "success"; an exploited one says "done" where the
simulator's own success check never fires.

    PYTHONPATH=. .venv/bin/python scripts/replay_imagined.py <collect> <tokenize> <train_wm> <sft> <rl> \\
        [--policy ppo] [--envs 24] [--steps 75]

Prints, per policy: imagined done rate (done head >= theta at any step), simulator success rate of
the replayed actions, and the 2x2 table of (imagined done, replayed success), with Wilson 95%
intervals.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in ("collect", "tokenize", "train_wm", "sft", "rl"):
        ap.add_argument(name, type=Path)
    ap.add_argument("--policy", choices=["ppo", "sft"], default="ppo")
    ap.add_argument("--envs", type=int, default=24, help="IND environments (spread over the 4 tasks)")
    ap.add_argument("--steps", type=int, default=75, help="policy steps (evaluate.max_steps)")
    ap.add_argument("--theta", type=float, default=0.5, help="done-head threshold (rl.theta_done)")
    ap.add_argument("--seed", type=int, default=2_000_000)
    ap.add_argument("--stochastic", action="store_true", help="sample the policy's actions (as PPO does in training)")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.collect.catalog import read_scenes_json
    from stages.evaluate.stats import wilson
    from stages.goals.environments import list_environments
    from stages.rl.sim_env import SimSpec, SimTaskEnv
    from stages.sft import TEXT_EMBEDDINGS
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, act, load_policy
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.rollout import load_world_model

    tok = load_tokenizer(args.tokenize, "cpu")
    obs_fn = ObservationFn(tok, json.loads((args.sft / TEXT_EMBEDDINGS).read_text()))
    wm = load_world_model(args.train_wm, "action", "cpu")
    k = int(wm.spec.frame_skip)
    model = load_policy(args.rl / "policy.zip" if args.policy == "ppo" else args.sft / POLICY_FILE, "cpu")
    catalog = read_scenes_json(args.collect / "scenes.json")
    envs = [e for e in list_environments(args.collect) if e.split == "ind"]
    by_task: dict[str, list] = {}
    for e in envs:
        by_task.setdefault(e.task, []).append(e)
    tasks = sorted(by_task)
    picked = [by_task[tasks[i % len(tasks)]][(i // len(tasks)) % len(by_task[tasks[i % len(tasks)]])]
              for i in range(args.envs)]

    # 1. the simulator's initial frames
    starts, specs, seeds, instructions, proprio0 = [], [], [], [], []
    sim = None
    for i, e in enumerate(picked):
        spec = SimSpec(e.task, catalog[e.scene_id].to_dict())
        if sim is None:
            sim = SimTaskEnv([spec], obs_fn, max_steps=args.steps, action_repeat=k, keep_frames=True)
        sim.keep_frames = True
        first, _ = sim.reset(seed=args.seed + i, options={"spec": spec})
        proprio0.append(first["proprio"])
        third, wrist = sim.frames[0]
        starts.append(tok.encode(third[None], wrist[None])[0])
        specs.append(spec)
        seeds.append(args.seed + i)
        instructions.append(sim.instruction)
    tokens0 = torch.stack([torch.as_tensor(t) for t in starts]).long()  # (N, h, w)

    # 2. imagine: the policy closed loop in the world model
    n = len(picked)
    roll = wm.rollout(n)
    roll.reset(tokens0)
    proprio = torch.as_tensor(np.stack(proprio0))  # (N, 10)
    obs = obs_fn.from_tokens(tokens0, proprio.numpy(), instructions)
    actions = np.zeros((n, args.steps, 7), np.float32)
    done_at = np.full(n, -1)
    with torch.no_grad():
        for t in range(args.steps):
            a = torch.as_tensor(act(model, obs, deterministic=not args.stochastic))
            a = torch.minimum(torch.maximum(a, wm.net.action_low), wm.net.action_high)  # what the WM sees (it clips)
            actions[:, t] = a.numpy()  # replayed as seen, so both environments get the same actions
            out = roll.step(a)
            proprio = wm.next_proprio(proprio, a, out.tokens)
            hit = (out.done_prob.cpu().numpy() >= args.theta) & (done_at < 0)
            done_at[hit] = t + 1
            obs = obs_fn.from_tokens(out.tokens, proprio.numpy(), instructions)

    # 3. replay the imagined actions in the simulator from the same initial states
    success = np.zeros(n, bool)
    sim.keep_frames = False
    for i in range(n):
        sim.reset(seed=seeds[i], options={"spec": specs[i]})
        horizon = done_at[i] if done_at[i] > 0 else args.steps
        for t in range(horizon):
            _, _, term, trunc, info = sim.step(actions[i, t])
            if info["success"]:
                success[i] = True
                break
            if trunc:
                break
    sim.close()

    done = done_at > 0
    print(f"policy {args.policy} ({'sampled' if args.stochastic else 'deterministic'} actions): {n} IND environments, horizon {args.steps} policy steps x {k} control steps")
    for name, x in (("imagined done (done head >= theta)", done), ("simulator success of the replayed actions", success)):
        _, lo, hi = wilson(int(x.sum()), n)
        print(f"  {name}: {x.sum()}/{n} = {x.mean():.2f} [{lo:.2f}, {hi:.2f}]")
    print("  (imagined done, replayed success) counts:",
          {f"({int(d)}, {int(s)})": int(((done == d) & (success == s)).sum()) for d in (1, 0) for s in (1, 0)})
    for i in range(n):
        print(f"    {specs[i].key:55s} done_at {done_at[i]:3d}  replay success {bool(success[i])}")


if __name__ == "__main__":
    main()
