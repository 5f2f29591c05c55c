"""Does the world model know when its imagination has gone wrong? A probe of its self-confidence.

Imagines a policy's episodes from fresh simulator starts and replays their actions in ManiSkill (the
rl stage's imagined-success check, ``stages.rl.imagined``), with a rollout that also records, for
every imagined frame, the world model's self-consistency: the mean probability its MaskGIT head
gives each token of the frame given all the others (one extra head pass per step). Prints

  - the third view's token accuracy against the replayed frames (the view that shows the object;
    the wrist camera moves with the arm) beside a still scene's (the first frame's),
  - the Spearman correlation, over (environment, step) pairs, of the confidence with the token
    accuracy of the whole frame,
  - the confidence at the imagined-done step of confirmed and of false imagined successes.

With ``--recorded`` it prints the third view's token accuracy for the planner's own actions instead:
the split's optimal demonstrations (held-out IND, or OOD) rolled from their first frames under their
recorded actions, against their recorded frames (no simulator, no policy).

    PYTHONPATH=. .venv/bin/python scripts/wm_confidence_probe.py <collect> <tokenize> <train_wm> <sft> <rl> \\
        [--policy ppo|sft] [--envs 48] [--split ind] [--recorded]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

STEPS_SHOWN = (1, 5, 10, 20)


def confident_rollout_class():
    from stages.train_wm.rollout import Rollout

    class ConfidentRollout(Rollout):
        """A rollout that keeps each decoded frame's mean token probability given the rest (B,) per step."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.confidence: list[torch.Tensor] = []

        def _decode(self, ctx: torch.Tensor) -> torch.Tensor:
            tok = super()._decode(ctx)  # (B, N)
            probs = torch.softmax(self.net.logits(self.net.head(ctx, tok)).float(), -1)  # (B, N, V)
            self.confidence.append(probs.gather(-1, tok[..., None])[..., 0].mean(1).cpu())  # (B,)
            return tok

    return ConfidentRollout


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    rank = lambda v: np.argsort(np.argsort(v)).astype(np.float64)  # noqa: E731
    return float(np.corrcoef(rank(x), rank(y))[0, 1])


@torch.no_grad()
def recorded_fidelity(collect, tokenize, train_wm, split: str, episodes: int) -> None:
    """Third-view token accuracy of the world model under the optimal demonstrations' recorded actions."""
    import json

    from stages.collect.dataset import Dataset
    from stages.common.frame_skip import compose_actions, frame_indices
    from stages.tokenize.store import TokenStore
    from stages.train_wm.rollout import load_world_model

    wm = load_world_model(train_wm, "action", "cpu")
    ds, store = Dataset(collect), TokenStore(tokenize)
    meta = {m.episode_id: m for m in ds.episodes}
    ids = json.loads((train_wm / "split.json").read_text())["heldout" if split == "ind" else "ood"]
    ids = [i for i in ids if meta[i].kind == "optimal"][:episodes]
    half, k_skip = wm.spec.grid[1], wm.spec.frame_skip
    acc: dict[int, list] = {k: [] for k in STEPS_SHOWN}
    still: dict[int, list] = {k: [] for k in STEPS_SHOWN}
    for i in ids:
        recorded = ds.load_states(i)["action"]  # (T, 7) control actions
        tokens = np.asarray(store.episode(i), dtype=np.int64)[frame_indices(len(recorded), k_skip)]  # (T'+1, h, w)
        actions = compose_actions(recorded, k_skip)  # (T', 7)
        roll = wm.rollout(1)
        roll.reset(torch.as_tensor(tokens[:1]))
        for t in range(min(max(STEPS_SHOWN), len(actions))):
            imagined = roll.step(torch.as_tensor(actions[t : t + 1])).tokens[0].numpy()  # (h, w)
            if t + 1 in acc:
                acc[t + 1].append(float((imagined[:half] == tokens[t + 1][:half]).mean()))
                still[t + 1].append(float((tokens[0][:half] == tokens[t + 1][:half]).mean()))
    print(f"recorded actions: {len(ids)} optimal {'held-out IND' if split == 'ind' else 'OOD'} demonstrations")
    print("  third view: tokens equal to the recorded frame's (a still scene's in brackets): " + ", ".join(
        f"{np.mean(acc[k]):.3f} ({np.mean(still[k]):.3f}) after {k}" for k in STEPS_SHOWN if acc[k]))


def main() -> None:
    from policy_check import add_artifact_args, load_check

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_artifact_args(ap, ("collect", "tokenize", "train_wm", "sft", "rl"))
    ap.add_argument("--policy", default="ppo", help="ppo (rl's policy.zip) or sft")
    ap.add_argument("--envs", type=int, default=48)
    ap.add_argument("--split", choices=["ind", "ood"], default="ind")
    ap.add_argument("--steps", type=int, default=75)
    ap.add_argument("--theta", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=2_000_000)
    ap.add_argument("--recorded", action="store_true",
                    help="the optimal demonstrations' recorded actions instead of the policy (up to --envs of them)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.recorded:
        recorded_fidelity(args.collect, args.tokenize, args.train_wm, args.split, args.envs)
        return

    from stages.rl.imagined import imagine_and_replay
    from stages.sft.policy import POLICY_FILE

    path = {"ppo": args.rl / "policy.zip", "sft": args.sft / POLICY_FILE}[args.policy]
    c = load_check(args.collect, args.tokenize, args.train_wm, args.sft, path, split=args.split, envs=args.envs,
                   steps=args.steps, wm_play=args.wm_play)
    if c.tok.grid[0] != 2 * c.tok.grid[1]:
        raise SystemExit(f"this probe needs the per-view tokenizer (two stacked grids), got grid {c.tok.grid}")
    cls = confident_rollout_class()
    rolls = []

    def rollout(n, seed=0):
        rolls.append(cls(c.wm, n, seed))
        return rolls[-1]

    c.wm.rollout = rollout  # the imagined-success check builds its rollout through this
    record: dict = {}
    try:
        rows = imagine_and_replay(c.policy, c.wm, c.tok, c.obs_fn, c.sim, c.specs,
                                  [args.seed + i for i in range(len(c.specs))], args.steps, args.theta, record=record)
    finally:
        c.sim.close()
    conf = torch.stack(rolls[-1].confidence, 1).numpy()  # (N, T) after each imagined step
    half = c.tok.grid[1]  # rows of one view's grid; the third view is on top
    imagined = record["tokens"][:, :, :half].numpy()  # (N, T+1, s, s) third view, imagined (frame 0 = real)

    print(f"policy {args.policy}: {len(rows)} {args.split.upper()} environments, horizon {args.steps}")
    third_acc: dict[int, list] = {k: [] for k in STEPS_SHOWN}
    third_copy: dict[int, list] = {k: [] for k in STEPS_SHOWN}
    pairs_conf, pairs_acc = [], []
    for i, r in enumerate(rows):
        frames = np.stack(record["frames"][i][1:])  # (L, H, W, 3) replayed third views after each step
        real = c.tok.encode(frames, frames)[:, :half].cpu().numpy()  # (L, s, s): the third view's tokens
        for k in STEPS_SHOWN:
            if len(real) >= k:
                third_acc[k].append(float((imagined[i, k] == real[k - 1]).mean()))
                third_copy[k].append(float((imagined[i, 0] == real[k - 1]).mean()))
        pairs_conf += list(conf[i, : len(r.token_accuracy)])
        pairs_acc += list(r.token_accuracy)
    print("  third view: tokens equal to the replayed frame's (a still scene's in brackets): " + ", ".join(
        f"{np.mean(third_acc[k]):.3f} ({np.mean(third_copy[k]):.3f}) after {k}" for k in STEPS_SHOWN if third_acc[k]))
    print(f"  confidence per step: mean {conf.mean():.3f}, after step 1 {conf[:, 0].mean():.3f}, "
          f"after step 20 {conf[:, min(19, conf.shape[1] - 1)].mean():.3f}")
    print(f"  Spearman(confidence, whole-frame token accuracy) over {len(pairs_acc)} (environment, step) pairs: "
          f"{spearman(np.array(pairs_conf), np.array(pairs_acc)):.3f}")
    fired = [(i, r) for i, r in enumerate(rows) if r.done_at > 0]
    for label, keep in (("confirmed", True), ("false", False)):
        vals = [conf[i, r.done_at - 1] for i, r in fired if r.success == keep]
        print(f"  {label} imagined successes: {len(vals)}" +
              (f", confidence at the done step mean {np.mean(vals):.3f} (min {np.min(vals):.3f}, max {np.max(vals):.3f})"
               if vals else ""))


if __name__ == "__main__":
    main()
