"""Is the world model a faithful environment for a closed-loop policy? The same policy, from the same
initial state, run closed loop in ManiSkill and inside the action world model, side by side.

For each picked environment: reset the simulator, run the policy (deterministic) closed loop in the
simulator for ``--steps`` policy steps; independently, tokenize the same first frame and run the
same policy closed loop inside the action world model (its frames and its proprioception head's
states are what the policy sees there, as in the rl stage's WorldModelVecEnv). Prints per
environment: the simulator's success step, the done head's peak probability and the step where it
first reached theta, and how far the world model's predicted TCP drifted from the simulator's
(which diverge as soon as the two trajectories do). Ends with the done head as a judge of the policy:
of the environments where it imagined a success, how many the policy really succeeded in, closed
loop (a looser test than the rl stage's open-loop replay of the imagined actions), against the rate
where it did not, within each task (``agreement``). Writes a frame strip (third view; per
environment a simulator row over a world-model row, every ``--every`` policy steps).

    PYTHONPATH=. .venv/bin/python scripts/wm_closed_loop.py <collect> <tokenize> <train_wm> <sft> \\
        [--policy PATH] [--envs 8] [--split ind] [--steps 40] [--every 5] [--out wm_closed_loop.png]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def agreement(summary: list[dict]) -> dict:
    """The done head as a judge of the policy: real closed-loop success where the world model imagined
    one (``precision``, Wilson 95%) and where it did not, overall and per task; per task too because
    imagined successes gather in the tasks the policy masters, so the overall precision mostly echoes
    those tasks' success rates. summary rows: {"env": "<task>/...", "sim_success_at", "wm_done_at"}."""
    from stages.evaluate.stats import wilson

    def cell(rows: list[dict]) -> dict:
        done = [r for r in rows if r["wm_done_at"] > 0]
        rest = [r for r in rows if r["wm_done_at"] <= 0]
        hit = sum(r["sim_success_at"] > 0 for r in done)
        p, lo, hi = wilson(hit, len(done)) if done else (None, None, None)
        return {"environments": len(rows), "real": sum(r["sim_success_at"] > 0 for r in rows),
                "imagined": len(done), "imagined_and_real": hit, "precision": p, "precision_lo": lo,
                "precision_hi": hi, "real_where_not_imagined": sum(r["sim_success_at"] > 0 for r in rest),
                "not_imagined": len(rest)}

    tasks = sorted({r["env"].split("/")[0] for r in summary})
    return {"all": cell(summary), **{t: cell([r for r in summary if r["env"].startswith(t + "/")]) for t in tasks}}


def main() -> None:
    from policy_check import add_artifact_args, add_decoding_options, load_check

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_artifact_args(ap)
    ap.add_argument("--policy", type=Path, default=None, help="a policy file (default: the sft artifact's policy)")
    ap.add_argument("--envs", type=int, default=8)
    ap.add_argument("--split", choices=["ind", "ood"], default="ind")
    ap.add_argument("--steps", type=int, default=40, help="policy steps in each environment")
    ap.add_argument("--every", type=int, default=5, help="strip: one frame every this many policy steps")
    ap.add_argument("--theta", type=float, default=0.5, help="done-head threshold (rl.theta_done)")
    add_decoding_options(ap)
    ap.add_argument("--seed", type=int, default=3_000_000)
    ap.add_argument("--out", type=Path, default=Path("wm_closed_loop.png"))
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.goals.figure import goal_grid, to_uint8
    from stages.sft.policy import POLICY_FILE, act

    c = load_check(args.collect, args.tokenize, args.train_wm, args.sft, args.policy or args.sft / POLICY_FILE,
                   split=args.split, envs=args.envs, steps=args.steps, keep_frames=True,
                   decode_steps=args.decode_steps, temperature=args.temperature, wm_play=args.wm_play)
    tok, obs_fn, wm, policy, specs, sim = c.tok, c.obs_fn, c.wm, c.policy, c.specs, c.sim
    shown = list(range(0, args.steps + 1, args.every))
    rows, summary = [], []
    try:
        for i, spec in enumerate(specs):
            seed = args.seed + i
            # the simulator, closed loop
            obs, _ = sim.reset(seed=seed, options={"spec": spec})
            third0, wrist0 = sim.frames[0]
            proprio0 = obs["proprio"].copy()  # (10,) the world model starts from the same robot state
            sim_frames, sim_tcp, sim_success_at = [third0], [proprio0[:3]], -1
            for t in range(args.steps):
                obs, _, term, trunc, info = sim.step(act(policy, {k: v[None] for k, v in obs.items()})[0])
                sim_frames.append(sim.frames[-1][0])
                sim_tcp.append(obs["proprio"][:3].copy())
                if info["success"] and sim_success_at < 0:
                    sim_success_at = t + 1
                if term or trunc:
                    break
            # the world model, closed loop from the same first frame
            tokens = torch.as_tensor(tok.encode(third0[None], wrist0[None])).long()  # (1, h, w)
            roll = wm.rollout(1)
            roll.reset(tokens)
            proprio = torch.as_tensor(proprio0[None])  # (1, 10)
            wobs = obs_fn.from_tokens(tokens, proprio.numpy(), [sim.instruction], first=tokens)
            wm_tokens, wm_tcp, peak, done_at = [tokens[0]], [proprio[0, :3].numpy().copy()], 0.0, -1
            for t in range(args.steps):
                a = torch.as_tensor(act(policy, wobs))
                a = torch.minimum(torch.maximum(a, wm.net.action_low), wm.net.action_high)
                out = roll.step(a)
                proprio = wm.next_proprio(proprio, a, out.tokens)
                p = float(out.done_prob[0])
                peak = max(peak, p)
                if p >= args.theta and done_at < 0:
                    done_at = t + 1
                wm_tokens.append(out.tokens[0])
                wm_tcp.append(proprio[0, :3].numpy().copy())
                wobs = obs_fn.from_tokens(out.tokens, proprio.numpy(), [sim.instruction], first=tokens)
            n = min(len(sim_tcp), len(wm_tcp))
            drift = [float(np.linalg.norm(wm_tcp[t] - sim_tcp[t]) * 10) for t in range(n)]  # dm -> cm
            summary.append({"env": spec.key, "sim_success_at": sim_success_at, "wm_done_at": done_at,
                            "wm_peak_done": round(peak, 3),
                            "tcp_drift_cm": {t: round(drift[t], 1) for t in (5, 10, 20, n - 1) if t < n}})
            wm_third, _ = tok.decode(torch.stack(wm_tokens))  # (T+1, 3, S, S) in [0, 1]
            rows.append((f"{spec.task} sim (success@{sim_success_at})",
                         [sim_frames[t] if t < len(sim_frames) else None for t in shown]))
            rows.append((f"world model (done@{done_at}, peak {peak:.2f})", [to_uint8(wm_third[t]) for t in shown]))
            print(json.dumps(summary[-1]), flush=True)
    finally:
        sim.close()
    goal_grid(rows, [f"t={t}" for t in shown], args.out, max_rows=len(rows))
    sims = sum(s["sim_success_at"] > 0 for s in summary)
    dones = sum(s["wm_done_at"] > 0 for s in summary)
    print(f"{len(summary)} {args.split.upper()} environments: simulator success {sims}, world-model done {dones}; "
          f"strip: {args.out}")
    for name, c in agreement(summary).items():
        p = "-" if c["precision"] is None else f"{c['precision']:.2f} [{c['precision_lo']:.2f}, {c['precision_hi']:.2f}]"
        print(f"  {name:12s} imagined success really succeeded closed loop: {c['imagined_and_real']}/{c['imagined']} "
              f"({p}); where none was imagined: {c['real_where_not_imagined']}/{c['not_imagined']}")


if __name__ == "__main__":
    main()
