"""Would a frame-only success classifier make imagined successes real?

Trains ``stages.train_wm.success_head`` (one frame's codes -> success, no temporal context, no
actions) on the train_wm artifact's training episodes, reports its AUROC and near-miss false alarms
on the held-out IND and the OOD episodes next to nothing else, then runs the imagined-success check
(``stages.rl.imagined``) for a policy and reads precision three ways from the same rollouts: with
the world model's done head (as the rl stage does), with the success head on the imagined frames,
and with both (the smaller of the two probabilities).

    PYTHONPATH=. .venv/bin/python scripts/success_head_probe.py <collect> <tokenize> <train_wm> <sft> \\
        [--policy PATH] [--envs 32] [--steps 75] [--head-steps 3000]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    from policy_check import add_artifact_args, load_check

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_artifact_args(ap)
    ap.add_argument("--policy", type=Path, default=None, help="a policy file (default: the sft artifact's policy)")
    ap.add_argument("--envs", type=int, default=32)
    ap.add_argument("--steps", type=int, default=75)
    ap.add_argument("--theta", type=float, default=0.5)
    ap.add_argument("--head-steps", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=2_000_000)
    ap.add_argument("--save", type=Path, default=None, help="save the trained success head here")
    args = ap.parse_args()
    torch.set_num_threads(2)

    from stages.rl.imagined import imagine_and_replay, precision_metrics, replay_row
    from stages.sft.policy import POLICY_FILE
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.data import load_episodes
    from stages.train_wm.evaluate import auroc
    from stages.train_wm.rollout import load_world_model
    from stages.train_wm.success_head import SuccessHead, labelled_frames, success_prob, train_success_head

    tok = load_tokenizer(args.tokenize, "cpu")
    frame_skip = int(load_world_model(args.train_wm, "action", "cpu").spec.frame_skip)
    split = json.loads((args.train_wm / "split.json").read_text())
    episodes = {e.episode_id: e for e in load_episodes(args.collect, args.tokenize, frame_skip=frame_skip)}
    codes_fn = lambda t: tok.codes(torch.from_numpy(t.reshape(len(t), *tok.grid)))  # noqa: E731
    train = [episodes[i] for i in split["train"]]
    head = SuccessHead(tok.bits, tok.grid)
    fit = train_success_head(head, labelled_frames(train, codes_fn), steps=args.head_steps, batch_size=256,
                             lr=1e-3, seed=0)
    print(f"success head: {len(train)} training episodes, {args.head_steps} steps in {fit['seconds']:.0f} s, "
          f"final loss {fit['final']:.3f}")
    if args.save:
        torch.save({"config": head.config(), "state_dict": head.state_dict()}, args.save)
    for name in ("heldout", "ood"):
        eps = [episodes[i] for i in split[name]]
        codes, labels = labelled_frames(eps, codes_fn)
        p = success_prob(head, codes).numpy()
        ends = np.cumsum([len(e.done) for e in eps])
        per_ep = np.split(p, ends[:-1])
        near = [q.max() >= args.theta for q, e in zip(per_ep, eps) if e.kind == "near_miss"]
        recall = [q[-1] >= args.theta for q, e in zip(per_ep, eps) if e.done[-1] > 0.5]
        print(f"  {name}: frames {len(p)}, AUROC {auroc(p, labels.numpy()):.3f}, success frames caught "
              f"{np.mean(recall):.2f} ({len(recall)} episodes), near-miss false alarms "
              f"{np.mean(near) if near else float('nan'):.2f} ({len(near)} episodes)")

    for sp in ("ind", "ood"):
        sft_policy = args.policy or args.sft / POLICY_FILE
        c = load_check(args.collect, args.tokenize, args.train_wm, args.sft, sft_policy, split=sp, envs=args.envs,
                       steps=args.steps, wm_play=args.wm_play)
        record = {}
        try:
            rows = imagine_and_replay(c.policy, c.wm, c.tok, c.obs_fn, c.sim, c.specs,
                                      [args.seed + i for i in range(len(c.specs))], args.steps, args.theta, record)
        finally:
            c.sim.close()
        tokens = record["tokens"][:, 1:]  # (N, T, h, w) imagined frames after each step
        n, t = tokens.shape[:2]
        frame_p = success_prob(head, tok.codes(tokens.reshape(n * t, *tok.grid))).view(n, t).numpy()
        for label, probs in (("done head", [np.asarray(r.done_probs) for r in rows]),
                             ("success head", list(frame_p)),
                             ("both", [np.minimum(np.asarray(r.done_probs), q) for r, q in zip(rows, frame_p)])):
            m = precision_metrics([replay_row(r.env_id, pr, r.first_success, args.theta) for r, pr in zip(rows, probs)])
            prec = "-" if m["precision"] is None else f"{m['precision']:.2f} [{m['precision_lo']:.2f}, {m['precision_hi']:.2f}]"
            print(f"  {sp} {label:12s}: imagined done {m['imagined_done']:2d} / {n}, confirmed "
                  f"{m['imagined_and_replayed']}, precision {prec}")
        print(f"  {sp}: replays that succeed anywhere {sum(r.first_success > 0 for r in rows)}")


if __name__ == "__main__":
    main()
