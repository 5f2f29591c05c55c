"""Imagined-success precision: does the policy exploit the world model?

For each picked (task, scene) environment: reset the simulator (a fresh seed), tokenize its first
frame, roll the policy closed-loop inside the action world model from that frame (deterministic
actions, clipped to the world model's action range as the world model clips them; the done head
read at every step), then replay exactly those actions open loop in the simulator from the same
initial state (each repeated ``frame_skip`` control steps, as in training) up to the step where
the done head fired. Precision = replayed successes among the imagined ones: a world model the
policy does not exploit says "done" where the simulator's success check fires too.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stages.evaluate.stats import wilson


@dataclass
class Replay:
    env_id: str
    done_at: int  # policy step at which the done head first reached theta, -1 if never
    success: bool  # the replayed actions succeeded in the simulator (by done_at, or the horizon)


def pick_environments(envs: list, n: int) -> list:
    """Up to ``n`` environments spread round-robin over their tasks (sorted), in a fixed order."""
    by_task: dict[str, list] = {}
    for e in envs:
        by_task.setdefault(e.task, []).append(e)
    tasks = sorted(by_task)
    if not tasks:
        return []
    return [by_task[tasks[i % len(tasks)]][(i // len(tasks)) % len(by_task[tasks[i % len(tasks)]])]
            for i in range(n)]


@torch.no_grad()
def imagine_and_replay(policy, wm, tok, obs_fn, sim, specs: list, seeds: list[int], steps: int,
                       theta: float) -> list[Replay]:
    """Imagine ``steps`` policy steps from each spec's simulator start, replay them in ``sim``.

    sim: a ``SimTaskEnv`` whose ``action_repeat`` is the world model's frame skip.
    """
    from stages.sft.policy import act

    starts, instructions, proprio0 = [], [], []
    sim.keep_frames = True
    for spec, seed in zip(specs, seeds):
        first, _ = sim.reset(seed=seed, options={"spec": spec})
        third, wrist = sim.frames[0]
        starts.append(torch.as_tensor(tok.encode(third[None], wrist[None])[0]))
        instructions.append(sim.instruction)
        proprio0.append(first["proprio"])
    sim.keep_frames = False
    n = len(specs)
    tokens = torch.stack(starts).long()  # (N, h, w)
    roll = wm.rollout(n)
    roll.reset(tokens)
    proprio = torch.as_tensor(np.stack(proprio0))  # (N, 10)
    obs = obs_fn.from_tokens(tokens, proprio.numpy(), instructions)
    actions = np.zeros((n, steps, 7), np.float32)
    done_at = np.full(n, -1)
    for t in range(steps):
        a = torch.as_tensor(act(policy, obs, deterministic=True))
        a = torch.minimum(torch.maximum(a, wm.net.action_low), wm.net.action_high)  # what the WM sees (it clips)
        actions[:, t] = a.numpy()  # replayed as seen, so both environments get the same actions
        out = roll.step(a)
        if getattr(wm, "proprio_head", None) is not None:
            proprio = wm.next_proprio(proprio, a, out.tokens)
        hit = (out.done_prob.cpu().numpy() >= theta) & (done_at < 0)
        done_at[hit] = t + 1
        if (done_at > 0).all():
            break
        obs = obs_fn.from_tokens(out.tokens, proprio.numpy(), instructions)

    out_rows = []
    for i, (spec, seed) in enumerate(zip(specs, seeds)):
        sim.reset(seed=seed, options={"spec": spec})
        success = False
        for t in range(done_at[i] if done_at[i] > 0 else steps):
            _, _, _, trunc, info = sim.step(actions[i, t])
            if info["success"]:
                success = True
                break
            if trunc:
                break
        out_rows.append(Replay(spec.key, int(done_at[i]), success))
    return out_rows


def precision_metrics(rows: list[Replay]) -> dict:
    """Counts, rates and Wilson intervals of imagined done, replayed success and precision."""
    done = np.array([r.done_at > 0 for r in rows])
    success = np.array([r.success for r in rows])
    both = int((done & success).sum())
    out = {"environments": len(rows), "imagined_done": int(done.sum()), "replayed_success": int(success.sum()),
           "imagined_and_replayed": both}
    p, lo, hi = wilson(both, int(done.sum())) if done.any() else (None, None, None)
    out.update({"precision": p, "precision_lo": lo, "precision_hi": hi})
    return out
