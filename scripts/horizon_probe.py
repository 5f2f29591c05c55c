"""Does the world model show the SFT policy succeeding when the success is k policy steps away?

The rl stage's calibration gate imagines the SFT policy for the whole horizon from first frames, and on
the two-round DAgger SFT it keeps pull alone: the tasks it drops (pick and place, move to aim) are the
ones whose real successes come late (median 25-30 policy steps against 11-13 for push and pull,
docs/RESULTS.md, session 95). This probe asks whether that is the distance: for each task, it starts
the same policy (deterministic actions) on its own imagined frames at the world-model frame ``k`` steps
before the first successful frame of an IND training demonstration that succeeded (the frame's
tokens and the robot's recorded proprioception, ``RLInputs.starts(any_frame=True)``), imagines
``k + --slack`` steps in the action world model (wm_play's fine-tuned one, as the rl stage does) and
counts the starts where the done head reached ``--theta``. No simulator runs: a demonstration reached
success from there in ``k`` steps, so a high rate says the model can show this policy finishing
from there, a low one that it cannot even this close. ``--actions demo`` replays the demonstration's
own recorded actions from the same frames instead (``k`` of them, then its last one repeated for the
slack): whether the model and its done head show the success when the actions are the ones that
really reached it, which separates the policy's imagined behaviour from the model's picture of the
task's end.

    PYTHONPATH=. .venv/bin/python scripts/horizon_probe.py <collect> <tokenize> <train_wm> <goals> <sft> \\
        <wm_play> [--k 5 10 20 30] [--actions policy|demo] [--per-task 32] [--slack 10] [--theta 0.5] [--seed 0] [--out probe.json]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

STAGES = ("collect", "tokenize", "train_wm", "goals", "sft", "wm_play")


def start_k_before(starts: list, k: int):
    """The start ``k`` frames before the first successful one, of one episode's starts before success
    (``starts[j]`` is frame j, the list ends just before the success), or None if it has fewer."""
    return starts[-k] if 1 <= k <= len(starts) else None


def demo_actions(actions: np.ndarray, start: int, steps: int) -> np.ndarray:
    """(steps, 7) the recorded world-model actions from frame ``start`` on (``actions`` (T', 7)), the last
    one repeated where the episode ends first."""
    a = actions[start:start + steps]
    return np.concatenate([a, np.repeat(a[-1:], steps - len(a), axis=0)]) if len(a) < steps else a


@torch.no_grad()
def replayed_successes(wm, tokens: np.ndarray, actions: np.ndarray, theta: float) -> np.ndarray:
    """(N,) bool: whether the done head reached ``theta`` while the world model imagined the recorded
    ``actions`` (N, T, 7) from ``tokens`` (N, h, w)."""
    roll = wm.rollout(len(tokens))
    roll.reset(torch.as_tensor(tokens).long().to(wm.device))
    done = np.zeros(len(tokens), bool)
    for t in range(actions.shape[1]):
        a = torch.as_tensor(actions[:, t], dtype=torch.float32, device=wm.device)
        a = torch.minimum(torch.maximum(a, wm.net.action_low), wm.net.action_high)  # as the rl env clips
        done |= roll.step(a).done_prob.float().cpu().numpy() >= theta
    return done


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in STAGES:
        ap.add_argument(name, type=Path, help=f"a committed {name} artifact directory")
    ap.add_argument("--k", type=int, nargs="+", default=[5, 10, 20, 30], help="policy steps before the success")
    ap.add_argument("--actions", choices=["policy", "demo"], default="policy",
                    help="the SFT policy closed loop (default), or the demonstration's recorded actions")
    ap.add_argument("--per-task", type=int, default=32, help="demonstrations per task (a seeded choice)")
    ap.add_argument("--slack", type=int, default=10, help="imagined steps beyond k")
    ap.add_argument("--theta", type=float, default=0.5, help="done-head threshold (rl.theta_done)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="write the table as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.rl import Config
    from stages.rl.calibration import imagined_successes
    from stages.rl.inputs import RLInputs

    dirs = {name: getattr(args, name) for name in STAGES}
    inp = RLInputs.load(SimpleNamespace(input=lambda name: dirs[name], device="cpu"), Config())
    inp.sft_policy.set_training_mode(False)  # deterministic actions, as the gate
    train = set(inp.split["train"])
    rng = np.random.default_rng(args.seed)
    rows = []
    for task in inp.tasks:
        demos = [(e, i) for e in inp.envs if e.task == task and e.split == "ind" for i in e.episodes
                 if i in train and inp.meta[i].success]
        pick = [demos[j] for j in sorted(rng.choice(len(demos), size=min(args.per_task, len(demos)), replace=False))]
        # one episode's starts before its success: an Environment holding that episode alone
        per_episode = [inp.starts([dataclasses.replace(e, episodes=[i])], any_frame=True) for e, i in pick]
        for k in args.k:
            starts = [s for s in (start_k_before(st, k) for st in per_episode) if s is not None]
            if not starts:
                done = np.zeros(0, bool)
            elif args.actions == "policy":
                done = imagined_successes(inp.sft_policy, inp.wm, inp.obs_fn, starts, k + args.slack, args.theta)
            else:
                near = [(i, st) for (_, i), st in zip(pick, per_episode) if start_k_before(st, k) is not None]
                acts = np.stack([demo_actions(inp.steps(i)[1], len(st) - k, k + args.slack)  # (N, k + slack, 7)
                                 for i, st in near])
                done = replayed_successes(inp.wm, np.stack([s.tokens for s in starts]), acts, args.theta)
            rows.append({"task": task, "k": k, "starts": len(starts), "imagined": int(done.sum()),
                         "rate": float(done.mean()) if len(done) else None})
            print(f"{task:12s} k={k:3d} ({args.actions}): imagined success {int(done.sum())}/{len(starts)} within {k + args.slack} steps",
                  flush=True)
    if args.out:
        keys = {name: dirs[name].name[:12] for name in STAGES}  # the artifacts' keys, not this machine's paths
        opts = {k: getattr(args, k) for k in ("k", "actions", "per_task", "slack", "theta", "seed")}
        args.out.write_text(json.dumps({"artifacts": keys, "options": opts, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
