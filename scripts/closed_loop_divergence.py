"""Where does the policy acting on its own imagined frames depart from the same policy in ManiSkill?

From the reset state of IND training demonstrations (the episode's seed, so the first frame is real
in both), the policy (deterministic) runs ``--steps`` policy steps in ManiSkill and, separately, the
same number closed loop in the action world model (wm_play's, as the rl stage uses). Per step it
prints the mean distance between the two arms' xyz commands, and two one-step, teacher-forced
causes along the simulator's trajectory: the policy's command when its frame is the model's
one-step prediction from the real history (proprioception real), and when its proprioception is the
proprioception head's one-step estimate (frame real). Also the TCP height 10 steps in, in the
simulator and as the proprioception head has chained it in the closed loop.

    PYTHONPATH=. .venv/bin/python scripts/closed_loop_divergence.py <collect> <tokenize> <train_wm> <goals> \\
        <sft> <wm_play> [--policy FILE] [--tasks pick_place move_to_aim] [--per-task 8] [--steps 20] [--seed 0]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

STAGES = ("collect", "tokenize", "train_wm", "goals", "sft", "wm_play")


@torch.no_grad()
def one_step_frame(wm, tokens: np.ndarray, actions: np.ndarray, t: int) -> np.ndarray:
    """(h, w) the model's frame ``t`` (>= 1) predicted from the real frames 0..t-1 (``tokens`` (T+1, h, w))
    and the actions 0..t-1 (``actions`` (T, 7)): teacher-forced up to t-1, imagined at t."""
    roll = wm.rollout(1)
    roll.reset(torch.as_tensor(tokens[:1]).long().to(wm.device))
    for u in range(t - 1):
        roll.step(torch.as_tensor(actions[u:u + 1], device=wm.device), next_tokens=torch.as_tensor(tokens[u + 1:u + 2]).long())
    return roll.step(torch.as_tensor(actions[t - 1:t], device=wm.device)).tokens[0].cpu().numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in STAGES:
        ap.add_argument(name, type=Path, help=f"a committed {name} artifact directory")
    ap.add_argument("--policy", type=Path, default=None, help="a policy file instead of the sft artifact's")
    ap.add_argument("--tasks", nargs="+", default=["pick_place", "move_to_aim"])
    ap.add_argument("--per-task", type=int, default=8, help="demonstrations' reset states per task (a seeded choice)")
    ap.add_argument("--steps", type=int, default=20, help="policy steps in each environment")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)

    from horizon_probe import probe_inputs, restore, sim_by_env, successful_demos
    from stages.sft.policy import act

    dirs = {name: getattr(args, name) for name in STAGES}
    inp = probe_inputs(dirs, args.policy)
    policy, wm, obs_fn = inp.sft_policy, inp.wm, inp.obs_fn
    sim, specs = sim_by_env(inp, dirs["collect"], args.steps, args.seed)
    rng = np.random.default_rng(args.seed)
    for task in args.tasks:
        pick = successful_demos(inp, task, args.per_task, rng)
        gaps = {"closed loop": [], "one-step frame": [], "one-step proprioception": []}
        heights = []
        for e, i in pick:
            obs = restore(sim, specs[e.env_id], inp.meta[i].seed, np.zeros((0, 7), np.float32))
            tokens, proprio, actions = [sim.tokens[0].numpy()], [obs["proprio"]], []
            sim.max_steps, sim.t = args.steps, 0
            for _ in range(args.steps):
                actions.append(act(policy, {k: v[None] for k, v in obs.items()})[0])
                obs, _, success, truncated, _ = sim.step(actions[-1])
                tokens.append(sim.tokens[0].numpy())
                proprio.append(obs["proprio"])
                if success or truncated:
                    break
            tokens, proprio, actions = np.stack(tokens), np.stack(proprio), np.stack(actions)  # (n+1, h, w), (n+1, 10), (n, 7)
            n, first, text = len(actions), tokens[:1], [e.instruction]
            roll = wm.rollout(1)
            roll.reset(torch.as_tensor(first).long().to(wm.device))
            p, o, imagined, chained = torch.as_tensor(proprio[:1]), obs_fn.from_tokens(first, proprio[:1], text, first=first), [], []
            for _ in range(n):  # closed loop in the model
                a = torch.as_tensor(act(policy, o), device=wm.device)
                a = torch.minimum(torch.maximum(a, wm.net.action_low), wm.net.action_high)
                out = roll.step(a)
                p = wm.next_proprio(p, a, out.tokens).cpu()
                imagined.append(a[0].cpu().numpy())
                chained.append(p[0].numpy())
                o = obs_fn.from_tokens(out.tokens.cpu().numpy(), p.numpy(), text, first=first)
            gaps["closed loop"].append(np.linalg.norm(np.stack(imagined)[1:, :3] - actions[1:, :3], axis=1))
            frame_gap, proprio_gap = [], []
            for t in range(1, n):  # one step, teacher-forced along the simulator's trajectory
                frame = one_step_frame(wm, tokens, actions, t)[None]
                head = wm.next_proprio(torch.as_tensor(proprio[t - 1:t]), torch.as_tensor(actions[t - 1:t]),
                                       torch.as_tensor(tokens[t:t + 1])).cpu().numpy()
                frame_gap.append(np.linalg.norm(act(policy, obs_fn.from_tokens(frame, proprio[t:t + 1], text, first=first))[0, :3] - actions[t, :3]))
                proprio_gap.append(np.linalg.norm(act(policy, obs_fn.from_tokens(tokens[t:t + 1], head, text, first=first))[0, :3] - actions[t, :3]))
            gaps["one-step frame"].append(np.asarray(frame_gap))
            gaps["one-step proprioception"].append(np.asarray(proprio_gap))
            k = min(10, n)
            heights.append((proprio[k, 2], chained[k - 1][2]))
        print(f"{task}: {len(pick)} reset states; mean |arm xyz command| difference at policy steps 1..9")
        for name, rows in gaps.items():
            long = [r[:9] for r in rows if len(r) >= 9]
            print(f"  {name:24s} {np.round(np.mean(long, axis=0), 3) if long else '-'} ({len(long)} episodes of >= 10 steps)")
        print(f"  TCP height 10 steps in (dm), simulator / closed loop: "
              + ", ".join(f"{s:.2f}/{c:.2f}" for s, c in heights))


if __name__ == "__main__":
    main()
