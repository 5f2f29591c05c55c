"""Do other world models, or the tokenizer, flag the imagined successes that are not real?

The rl stage's imagined-success check (``stages.rl.imagined``) finds most of a PPO policy's imagined
successes false: the replayed actions do not succeed in ManiSkill. A guard needs a signal that
separates the false ones from the true ones *from imagination alone*. This script rolls a policy
closed-loop in one action world model (``train_wm``'s ``action_wm.pt``), replays the actions in the
simulator as the stage does, and reads two candidate signals along every imagined episode:

- **ensemble disagreement**: each ``--members`` checkpoint (another action world model, e.g. trained
  with another seed by ``scripts/wm_ablation.py --save``) is fed the same actions and, as context,
  the *imagined* frames; at every step it predicts the next frame itself and reads the imagined one
  with its own done head. Disagreement = fraction of tokens where its prediction differs from the
  imagined frame; its done probability is a second opinion on the success.
- **tokenizer consistency**: the imagined frame decoded to pixels and encoded again; the fraction
  of tokens that come back unchanged (real frames are near fixed points; smears may not be).

For the imagined successes it prints each signal at the success step, true (replayed success) vs
false, and the AUROC of each signal for telling them apart (0.5 = no information), with the
precision a veto at the signal's median would leave.

    PYTHONPATH=. .venv/bin/python scripts/wm_disagreement.py <collect> <tokenize> <train_wm> <sft> \\
        --policy <rl>/policy.zip --members FILE [FILE ...] [--split ind] [--envs 48] [--seed 3000000]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


@torch.no_grad()
def member_signals(member, tokens: torch.Tensor, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A second action world model along imagined frames.

    tokens (N, T+1, h, w) the imagined episode (frame 0 real); actions (N, T, 7).
    Returns (disagreement (N, T): fraction of tokens its own next-frame prediction gets different
    from the imagined frame, done (N, T): its done head on the imagined frame).
    """
    n, t1 = tokens.shape[:2]
    roll = member.rollout(n)
    roll.reset(tokens[:, 0].to(member.device))
    net = member.net
    dis, done = np.zeros((n, t1 - 1), np.float32), np.zeros((n, t1 - 1), np.float32)
    for t in range(t1 - 1):
        a = torch.as_tensor(actions[:, t], device=member.device)
        kv = net.memory_kv(net.memory(roll._clip(a)[:, None]), 1)
        ctx = net.backbone(roll.frame[:, None], None, cache=roll.cache, kv=kv).view(n, net.spec.tokens, -1)
        roll.cache.step += 1
        pred = roll._decode(ctx)  # (N, h*w) its own next frame
        seen = tokens[:, t + 1].reshape(n, -1).to(member.device)  # (N, h*w) the imagined one
        logit, _ = net.done_logit(net.head(ctx, seen))
        dis[:, t] = (pred != seen).float().mean(1).cpu().numpy()
        done[:, t] = torch.sigmoid(logit).cpu().numpy()
        roll.frame = seen  # the imagined frame is the context of the next step
    return dis, done


@torch.no_grad()
def tokenizer_consistency(tok, tokens: torch.Tensor) -> np.ndarray:
    """Fraction of each frame's tokens unchanged by decode -> encode. tokens (N, T+1, h, w) -> (N, T+1)."""
    n, t1 = tokens.shape[:2]
    flat = tokens.reshape(n * t1, *tokens.shape[2:])
    third, wrist = tok.decode(flat)  # (M, 3, S, S) each in [0, 1]
    to_u8 = lambda x: (x * 255).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1)  # noqa: E731
    again = tok.encode(to_u8(third), to_u8(wrist)).cpu()  # (M, h, w)
    return (again == flat).float().mean((1, 2)).view(n, t1).numpy()


def auroc(pos: np.ndarray, neg: np.ndarray) -> float | None:
    """P(a positive scores above a negative), ties half; None without both classes."""
    if len(pos) == 0 or len(neg) == 0:
        return None
    diff = np.asarray(pos)[:, None] - np.asarray(neg)[None, :]
    return float((diff > 0).mean() + 0.5 * (diff == 0).mean())


def main() -> None:
    from policy_check import add_artifact_args, load_check

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_artifact_args(ap)
    ap.add_argument("--policy", type=Path, required=True, help="policy file (an rl artifact's policy.zip)")
    ap.add_argument("--members", type=Path, nargs="+", required=True, help="other action world-model checkpoints")
    ap.add_argument("--split", choices=["ind", "ood"], default="ind")
    ap.add_argument("--envs", type=int, default=48)
    ap.add_argument("--steps", type=int, default=75)
    ap.add_argument("--theta", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=3_000_000)
    ap.add_argument("--json", type=Path, default=None, help="write per-environment signals here")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.rl.imagined import imagine_and_replay
    from stages.train_wm.rollout import WorldModel, load_net

    c = load_check(args.collect, args.tokenize, args.train_wm, args.sft, args.policy, split=args.split,
                   envs=args.envs, steps=args.steps, wm_play=args.wm_play)
    import stages.sft.policy as sft_policy

    record: dict = {}
    # imagine_and_replay does not return its actions; recording them here leaves stages/rl (and so
    # every rl artifact's key) untouched. The wrapper is removed in `finally`.
    taken: list[np.ndarray] = []  # (N, 7) per step: the actions imagine_and_replay asks the policy for
    act = sft_policy.act
    sft_policy.act = lambda *a, **k: taken.append(np.asarray(act(*a, **k), np.float32)) or taken[-1]
    try:
        rows = imagine_and_replay(c.policy, c.wm, c.tok, c.obs_fn, c.sim, c.specs,
                                  [args.seed + i for i in range(len(c.specs))], args.steps, args.theta, record=record)
    finally:
        sft_policy.act = act
        c.sim.close()
    tokens = record["tokens"]  # (N, T+1, h, w)
    low, high = c.wm.net.action_low.cpu().numpy(), c.wm.net.action_high.cpu().numpy()
    actions = np.clip(np.stack(taken, 1), low, high)  # (N, T, 7) as the world model saw them
    consistency = tokenizer_consistency(c.tok, tokens)  # (N, T+1)
    print(f"tokenizer consistency of the real first frames: {consistency[:, 0].mean():.3f}", flush=True)
    signals = {"consistency": consistency[:, 1:]}  # (N, T) the imagined frames'
    for k, path in enumerate(args.members):
        m = WorldModel(load_net(path), c.wm.decode_steps, c.wm.temperature)
        signals[f"m{k}_disagreement"], signals[f"m{k}_done"] = member_signals(m, tokens, actions)
    if len(args.members) > 1:
        signals["mean_disagreement"] = np.mean([signals[f"m{k}_disagreement"] for k in range(len(args.members))], 0)
        signals["min_done"] = np.min([signals[f"m{k}_done"] for k in range(len(args.members))], 0)

    imagined = [i for i, r in enumerate(rows) if r.done_at > 0]
    true = [i for i in imagined if rows[i].success]
    false = [i for i in imagined if not rows[i].success]
    print(f"{args.split}: {len(rows)} environments, {len(imagined)} imagined successes, {len(true)} real", flush=True)
    for name, s in signals.items():
        at = {i: float(s[i, rows[i].done_at - 1]) for i in imagined}  # at the success step
        upto = {i: float(s[i, : rows[i].done_at].mean()) for i in imagined}  # mean over the episode until then
        # higher = "more likely real": consistency and done as they are, disagreement negated
        sign = -1.0 if "disagreement" in name else 1.0
        for label, d in (("at", at), ("upto", upto)):
            pos = np.array([sign * d[i] for i in true])
            neg = np.array([sign * d[i] for i in false])
            auc = auroc(pos, neg)
            med = np.median([sign * d[i] for i in imagined]) if imagined else 0.0
            kept_t, kept_f = int((pos >= med).sum()), int((neg >= med).sum())
            print(f"  {name:18s} {label:4s} true {np.mean([d[i] for i in true]) if true else float('nan'):.3f} "
                  f"false {np.mean([d[i] for i in false]) if false else float('nan'):.3f} "
                  f"AUROC {auc if auc is None else round(auc, 3)} | veto below median keeps {kept_t} real / {kept_t + kept_f}",
                  flush=True)
    if args.json:
        args.json.write_text(json.dumps({"split": args.split, "rows": [
            {"env": r.env_id, "done_at": r.done_at, "success": r.success, "first_success": r.first_success,
             **{k: [round(float(v), 4) for v in s[i]] for k, s in signals.items()}} for i, r in enumerate(rows)]}) + "\n")


if __name__ == "__main__":
    main()
