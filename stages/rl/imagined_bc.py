"""Behaviour cloning on imagined observations: the SFT policy taught to act on the world model's frames.

On seed 0, the SFT policy succeeds from a demonstration's state 5 policy steps before its success in 30 of 32
move-to-aim starts in ManiSkill (28-30 over seeds 0-2), and the action world model fed the actions it took there shows 30 of those 30
successes; acting on its own imagined frames from the same state it is shown succeeding in 7
(``scripts/horizon_probe.py --actions sim``, docs/RESULTS.md, session 96). The model pictures what the
policy does; the policy does something else when it reads the model's frames and the proprioception
head's estimate instead of the simulator's. PPO in the world model then trains a policy that is not the
one the simulator will run, and the calibration gate drops the tasks where the gap is widest.

This module closes the gap on the data SFT learned from: each training demonstration is imagined open
loop under its own recorded actions, restarted from the real frame every ``horizon`` steps, so each
frame of it gets an imagined twin 1..horizon steps from the last real frame (the world model's frame and
the proprioception head's chained estimate: what the policy reads inside the world model that many
steps into an episode). The policy is then fine-tuned with the sft stage's loss on the real pairs and
their imagined twins together (the demonstrated action is the target for both: the imagined frame
pictures the state the action was taken in).

Measured on seed 0 (docs/RESULTS.md, session 96, predictions 29-31): with restarts every 8 steps the
closed loop's move to aim from 5 steps away rose from 7 to 21 of 32 and the adapted policy equals SFT in
ManiSkill, but from first frames the calibration gate still kept pull alone and PPO gained nothing; with
restarts every 32 steps the adapted policy itself lost 0.05-0.07. Off by default (``rl.imagined_bc_epochs: 0``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stages.common.action_space import executed


@dataclass(frozen=True)
class Chunk:
    """One imagined stretch: demonstration ``demo``, from its real frame ``start`` for ``steps`` steps."""

    demo: int
    start: int
    steps: int


def chunks(lengths: list[int], horizon: int) -> list[Chunk]:
    """The stretches that give every frame j >= 1 with an action after it (1 <= j < T') one imagined twin:
    restarts at frames 0, horizon, 2 horizon, ... of each demonstration of ``lengths`` (T' actions each)."""
    if horizon < 1:
        raise ValueError(f"the imagined horizon must be >= 1, got {horizon}")
    out = []
    for d, n in enumerate(lengths):
        for a in range(0, n - 1, horizon):
            out.append(Chunk(d, a, min(horizon, n - 1 - a)))
    return out


@torch.no_grad()
def imagined_twins(wm, demos: list, horizon: int, batch: int = 256) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Imagine ``demos`` (``stages.sft.data.Demo``) under their recorded actions, restarting from the real
    frame every ``horizon`` steps. Returns (tokens (M, h, w), proprio (M, 10), index (M, 2)): the imagined
    frame and proprioception of demonstration ``index[:, 0]``'s frame ``index[:, 1]``, for every frame
    1 <= j < T' of every demonstration, in chunk order."""
    cs = chunks([len(d.actions) for d in demos], horizon)
    toks, props, idx = [], [], []
    for lo in range(0, len(cs), batch):
        part = cs[lo:lo + batch]
        tokens = torch.as_tensor(np.stack([demos[c.demo].tokens[c.start] for c in part])).long()  # (B, h, w)
        proprio = torch.as_tensor(np.stack([demos[c.demo].proprio[c.start] for c in part]), dtype=torch.float32)  # (B, 10)
        roll = wm.rollout(len(part))
        roll.reset(tokens.to(wm.device))
        for m in range(max(c.steps for c in part)):
            a = np.stack([demos[c.demo].actions[c.start + min(m, c.steps - 1)] for c in part])  # (B, 7); past a chunk's end: ignored
            a = torch.as_tensor(executed(a), dtype=torch.float32, device=wm.device)
            a = torch.minimum(torch.maximum(a, wm.net.action_low), wm.net.action_high)  # what the WM sees (it clips)
            out = roll.step(a)
            proprio = wm.next_proprio(proprio, a, out.tokens).cpu()  # (B, 10)
            for b, c in enumerate(part):
                if m < c.steps:
                    toks.append(out.tokens[b].cpu().numpy())
                    props.append(proprio[b].numpy())
                    idx.append((c.demo, c.start + m + 1))
    if not idx:
        raise ValueError("imagined BC: the demonstrations have no frame to imagine (each needs >= 2 actions)")
    return np.stack(toks).astype(np.int64), np.stack(props).astype(np.float32), np.asarray(idx, np.int64)


def imagined_pairs(wm, obs_fn, demos: list, horizon: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(obs: key -> (M, ...), actions (M, 7)): every imagined twin of ``imagined_twins`` with the action
    the demonstration took at that frame."""
    tokens, proprio, idx = imagined_twins(wm, demos, horizon)
    instructions = [demos[d].instruction for d, _ in idx]
    first = np.stack([demos[d].tokens[0] if demos[d].first is None else np.asarray(demos[d].first) for d, _ in idx])
    obs = obs_fn.from_tokens(tokens, proprio, instructions, first=first)
    actions = np.stack([demos[d].actions[j] for d, j in idx]).astype(np.float32)  # (M, 7)
    return obs, actions


def joined(a: tuple[dict, np.ndarray], b: tuple[dict, np.ndarray]) -> tuple[dict, np.ndarray]:
    """Two pair sets as one (the real pairs and their imagined twins)."""
    return {k: np.concatenate([a[0][k], b[0][k]]) for k in a[0]}, np.concatenate([a[1], b[1]])
