"""Imagined-success precision: does the policy exploit the world model?

For each picked (task, scene) environment: reset the simulator (a fresh seed), tokenize its first
frame, roll the policy closed-loop inside the action world model from that frame (deterministic
actions, clipped to the world model's action range as the world model clips them; the done head
read at every step), then replay exactly those actions open loop in the simulator from the same
initial state (each repeated ``frame_skip`` control steps, as in training) up to the step where
the done head fired. Precision = replayed successes among the imagined ones: a world model the
policy does not exploit says "done" where the simulator's success check fires too.

Each row also keeps the done head's probability at every imagined step and the step at which the
replayed actions first succeed over the whole horizon, so precision at any stricter threshold
(``precision_at``) comes from the same rollouts. ``tcp_error`` is the world model's arm fidelity
under the policy's own actions: after each replayed step, the distance between the TCP position the
world model predicted (its proprioception head) and the simulator's, for the same action sequence.
``token_accuracy`` is the same for the frames: the fraction of the imagined frame's tokens equal to
those of the replayed frame (the simulator's views through the tokenizer, as the policy sees them),
and ``copy_accuracy`` the fraction of the *first* frame's tokens equal to the replayed frame's: a
world model that imagined nothing at all (a still scene) scores it, so the frames' fidelity is the
gap between the two.

With a ``guard`` (``stages.rl.guard``), an imagined success is what the guarded environment counts
as one: the done head *and* the guard ensemble's mean probability at or above the threshold at the
same step, i.e. the smaller of the two probabilities is the step's success probability
(``done_probs``); the done head's own probabilities are kept as ``head_probs`` so precision without
the guard's veto comes from the same rollouts.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stages.common.proprio import POSITION_SCALE
from stages.evaluate.stats import wilson

STRICTER_THETAS = (0.7, 0.9, 0.97)  # done-head thresholds the rl stage also reports precision at
PERSIST_STEPS = (3,)  # and "done" held for this many consecutive imagined steps at the stage's threshold
TCP_ERROR_STEPS = (5, 10, 20)  # policy steps after which the rl stage reports the imagined TCP's error


@dataclass
class Replay:
    env_id: str
    done_at: int  # policy step at which the done head first reached theta, -1 if never
    success: bool  # the replayed actions succeeded in the simulator (by done_at, or the horizon)
    first_success: int = -1  # policy step of the replay's first simulator success over the horizon, -1 if never
    done_probs: tuple = ()  # success probability after each imagined step: the done head's (with a guard: min(head, guard))
    tcp_error: tuple = ()  # metres between imagined and replayed TCP after each step (until the replay ends)
    head_probs: tuple = ()  # with a guard: the done head's own probability after each step (done_probs is min(head, guard))
    token_accuracy: tuple = ()  # fraction of imagined tokens equal to the replayed frame's after each step (until it ends)
    copy_accuracy: tuple = ()  # the same for the first frame's tokens: what imagining a still scene would score


@dataclass
class ImaginedStep:
    """One step of a policy acting closed loop inside the world model (all envs of the batch)."""

    t: int  # 0-based step index
    action: np.ndarray  # (N, 7) the actions as the world model saw them (clipped to its range)
    out: object  # the rollout's step output: tokens (N, h, w), done_prob (N,), hidden (N, D)
    proprio: np.ndarray  # (N, 10) the robot's imagined proprioception after the step (the start's without a head)
    obs: dict  # the policy's observation of the imagined frame


@torch.no_grad()
def closed_loop(policy, wm, obs_fn, tokens: torch.Tensor, proprio0: np.ndarray, instructions: list[str], steps: int):
    """Yield ``ImaginedStep`` for ``steps`` steps of ``policy`` (deterministic actions) acting on its own
    imagined frames from ``tokens`` (N, h, w) and proprioception ``proprio0`` (N, 10): the loop the
    imagined-success check and the calibration gate (``stages.rl.calibration``) share."""
    from stages.sft.policy import act

    tokens = tokens.long().cpu()
    roll = wm.rollout(len(tokens))
    roll.reset(tokens.to(wm.device))
    has_head = getattr(wm, "proprio_head", None) is not None
    proprio = torch.as_tensor(np.asarray(proprio0))  # (N, 10) on the CPU (the head's output is brought back)
    obs = obs_fn.from_tokens(tokens, proprio.numpy(), instructions, first=tokens)
    for t in range(steps):
        a = torch.as_tensor(act(policy, obs, deterministic=True), device=wm.device)
        a = torch.minimum(torch.maximum(a, wm.net.action_low), wm.net.action_high)  # what the WM sees (it clips)
        out = roll.step(a)
        if has_head:
            proprio = wm.next_proprio(proprio, a, out.tokens).cpu()
        obs = obs_fn.from_tokens(out.tokens, proprio.numpy(), instructions, first=tokens)
        yield ImaginedStep(t, a.cpu().numpy(), out, proprio.numpy(), obs)


@torch.no_grad()
def imagine_and_replay(policy, wm, tok, obs_fn, sim, specs: list, seeds: list[int], steps: int,
                       theta: float, record: dict | None = None, guard=None, persist: int = 1) -> list[Replay]:
    """Imagine ``steps`` policy steps from each spec's simulator start, replay them in ``sim``.

    sim: a ``SimTaskEnv`` whose ``action_repeat`` is the world model's frame skip.
    record: if given, filled with ``tokens`` (N, T+1, h, w), the imagined frames' tokens, ``hidden``
    (N, T, D), their pooled head features (what the done head and the guard read), ``proprio``
    (N, T, 10), the imagined proprioception after each step (the start's throughout without a proprio
    head), ``frames``, per environment the replay's third-view frames (H, W, 3) uint8 at steps 0, 1,
    ... (until it ended), for looking at the two side by side, and ``replay_proprio``, per
    environment the replay's proprioception (10,) after steps 1, 2, ... (until it ended).
    guard: a ``stages.rl.guard.Guard`` the environment applies; an imagined success then needs its
    confirmation too (see the module docstring).
    persist: an imagined success needs that many consecutive steps at or above ``theta`` (the env's
    ``done_persist``).
    """
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
    tokens = torch.stack(starts).long().cpu()  # (N, h, w)
    actions = np.zeros((n, steps, 7), np.float32)
    probs = np.zeros((n, steps), np.float32)  # (N, T) done head after each step
    confirm = np.ones((n, steps), np.float32)  # (N, T) the guard ensemble's mean probability (1 without a guard)
    has_head = getattr(wm, "proprio_head", None) is not None  # without one the arm is not predicted: no tcp_error
    tcp = np.zeros((n, steps, 3), np.float32)  # (N, T, 3) imagined TCP position after each step
    first_codes = tok.codes(tokens).cpu().numpy() > 0  # (N, bits, h, w) bool: the frames' bits, whatever the policy reads
    codes = np.zeros((n, steps) + first_codes.shape[1:], bool)  # (N, T, C, h, w) the imagined frames' bits
    for s in closed_loop(policy, wm, obs_fn, tokens, np.stack(proprio0), instructions, steps):  # the whole horizon,
        t = s.t  # so stricter thresholds can be read off later
        actions[:, t] = s.action  # replayed as seen, so both environments get the same actions
        probs[:, t] = s.out.done_prob.cpu().numpy()
        if guard is not None:
            confirm[:, t] = guard.ensemble.probs(s.out.hidden).mean(0).cpu().numpy()  # (K, N) -> (N,)
        tcp[:, t] = s.proprio[:, :3]
        if record is not None:
            record.setdefault("tokens", [tokens]).append(s.out.tokens.cpu().long())
            record.setdefault("hidden", []).append(s.out.hidden.float().cpu())
            record.setdefault("proprio", []).append(s.proprio.copy())
        codes[:, t] = tok.codes(s.out.tokens).cpu().numpy() > 0

    if record is not None:
        record["tokens"] = torch.stack(record["tokens"], 1)  # (N, T+1, h, w)
        record["hidden"] = torch.stack(record["hidden"], 1)  # (N, T, D) the imagined frames' pooled head features
        record["proprio"] = np.stack(record["proprio"], 1)  # (N, T, 10) imagined proprioception after each step
        record["frames"], record["replay_proprio"] = [], []
        sim.keep_frames = True
    out_rows = []
    for i, (spec, seed) in enumerate(zip(specs, seeds)):
        sim.reset(seed=seed, options={"spec": spec})
        if record is not None:
            record["frames"].append([sim.frames[0][0]])
            record["replay_proprio"].append([])
        first_success, err, acc, copy = -1, [], [], []
        for t in range(steps):
            real, _, _, trunc, info = sim.step(actions[i, t])
            if record is not None:
                record["frames"][-1].append(sim.frames[-1][0])
                record["replay_proprio"][-1].append(np.asarray(real["proprio"], np.float32))
            if has_head:
                err.append(float(np.linalg.norm(np.asarray(real["proprio"])[:3] - tcp[i, t])) / POSITION_SCALE)  # dm -> m
            seen = tok.codes(sim.tokens)[0].cpu().numpy() > 0  # (bits, h, w) the replayed frame's
            acc.append(token_match(codes[i, t], seen))
            copy.append(token_match(first_codes[i], seen))
            if info["success"]:
                first_success = t + 1
                break
            if trunc:
                break
        err = tuple(round(e, 4) for e in err)
        row = (replay_row(spec.key, probs[i], first_success, theta, err, persist) if guard is None
               else guarded_row(spec.key, probs[i], confirm[i], first_success, theta, err, persist))
        row.token_accuracy, row.copy_accuracy = tuple(round(a, 4) for a in acc), tuple(round(c, 4) for c in copy)
        out_rows.append(row)
    sim.keep_frames = False
    return out_rows


def token_match(a: np.ndarray, b: np.ndarray) -> float:
    """Fraction of grid cells whose code bits all agree. a, b (C, h, w) bool -> float."""
    return float((a == b).all(0).mean())


def _first_at_least(probs: np.ndarray, theta: float, persist: int = 1) -> int:
    """First step (1-based) ending a run of ``persist`` consecutive probabilities >= theta, -1 if none."""
    above = np.asarray(probs) >= theta
    run = 0
    for t, a in enumerate(above):
        run = run + 1 if a else 0
        if run >= persist:
            return t + 1
    return -1


def replay_row(env_id: str, probs: np.ndarray, first_success: int, theta: float, tcp_error: tuple = (),
               persist: int = 1) -> Replay:
    """One environment's row from a success probability after each imagined step (the done head's, or
    any other read on the same imagined frames) and the replay's first simulator success; with
    ``persist`` > 1 the imagined success needs that many consecutive steps at or above ``theta``."""
    done_at = _first_at_least(probs, theta, persist)
    success = first_success > 0 and (done_at < 0 or first_success <= done_at)
    return Replay(env_id, done_at, success, first_success, tuple(round(float(p), 4) for p in probs), tcp_error)


def guarded_row(env_id: str, head: np.ndarray, confirm: np.ndarray, first_success: int, theta: float,
                tcp_error: tuple = (), persist: int = 1) -> Replay:
    """A row as the guarded environment counts success: the done head (T,) and the guard ensemble's mean
    probability (T,) both at or above ``theta`` at the same step; the head's own probabilities kept."""
    row = replay_row(env_id, np.minimum(head, confirm), first_success, theta, tcp_error, persist)
    row.head_probs = tuple(round(float(p), 4) for p in head)
    return row


def tcp_error_at(rows: list[Replay], steps: tuple[int, ...]) -> dict[int, float | None]:
    """Mean imagined-vs-replayed TCP distance (metres) after each of ``steps`` policy steps, over the
    rows whose replay lasted that long (None where none did)."""
    out = {}
    for k in steps:
        errs = [r.tcp_error[k - 1] for r in rows if len(r.tcp_error) >= k]
        out[k] = float(np.mean(errs)) if errs else None
    return out


def tcp_gap_to_done(row: Replay) -> float | None:
    """The largest imagined-vs-replayed TCP distance (metres) up to the row's imagined done, or up to
    the replay's end where that came first (a replay stops at its first success); None for a row
    with no imagined done or no TCP record. How far the imagined proprioception's TCP (the
    proprioception head's, driven mostly by the actions) had drifted from the real arm when the world
    model called the episode a success; the arm drawn in the imagined frames is another matter
    (scripts/arm_consistency_probe.py locates it)."""
    if row.done_at < 0 or not row.tcp_error:
        return None
    return float(max(row.tcp_error[: row.done_at]))


def tcp_gap_by_outcome(rows: list[Replay]) -> dict[str, list[float]]:
    """``tcp_gap_to_done`` of the imagined successes, split by whether the replay confirmed them:
    {"true": [...], "false": [...]} in metres, each sorted. Whether a drifted imagined arm marks
    the false ones is what a kinematic check on imagined episodes would rest on."""
    out = {"true": [], "false": []}
    for r in rows:
        gap = tcp_gap_to_done(r)
        if gap is not None:
            out["true" if r.success else "false"].append(gap)
    return {k: sorted(v) for k, v in out.items()}


def token_accuracy_at(rows: list[Replay], steps: tuple[int, ...]) -> dict[int, tuple[float, float] | None]:
    """Mean (imagined, first-frame) token accuracy against the replayed frame after each of ``steps``
    policy steps, over the rows whose replay lasted that long (None where none did)."""
    out = {}
    for k in steps:
        pairs = [(r.token_accuracy[k - 1], r.copy_accuracy[k - 1]) for r in rows if len(r.token_accuracy) >= k]
        out[k] = tuple(float(v) for v in np.mean(pairs, 0)) if pairs else None
    return out


def precision_at(rows: list[Replay], theta: float, persist: int = 1) -> dict:
    """``precision_metrics`` had the done head's threshold been ``theta``, held for ``persist`` steps
    (from the recorded probabilities)."""
    return precision_metrics([replay_row(r.env_id, np.asarray(r.done_probs), r.first_success, theta, r.tcp_error,
                                         persist) for r in rows])


def precision_head_only(rows: list[Replay], theta: float, persist: int = 1) -> dict:
    """``precision_metrics`` from the done head alone, without the guard's veto (rows imagined with a guard)."""
    if any(not r.head_probs for r in rows):
        raise ValueError("precision_head_only needs rows imagined with a guard (their head_probs are empty)")
    return precision_metrics([replay_row(r.env_id, np.asarray(r.head_probs), r.first_success, theta, (), persist)
                              for r in rows])


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
