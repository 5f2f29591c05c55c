"""Action-WM ablation on existing collect + tokenize artifacts: train the action WM only with some
train_wm config overrides, then open-loop PSNR / LPIPS / token accuracy at horizons 1, 5, 15 on
held-out IND and OOD episodes, next to copy-last, shuffled actions and the tokenizer ceiling.

    PYTHONPATH=. .venv/bin/python scripts/wm_ablation.py <collect_dir> <tokenize_dir> '{"frame_skip": 4}' [--save FILE]

``--save FILE`` also writes the trained action WM as a checkpoint (the stage's format): with a
different ``seed`` in the overrides, an independently trained member for an ensemble check
(``scripts/wm_disagreement.py``). ``--load FILE`` skips training and evaluates a saved checkpoint
(e.g. the stage's ``action_wm.pt``) on the same starts, the like-for-like baseline of a trained row.

Uses the stage's own functions (load_episodes, ClipSampler, train_world_model, horizon_eval); the
held-out IND list is the tokenizer's, OOD is capped at 6 episodes, 6 starts per episode.
"""
import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

import stages.train_wm as W
from stages.collect.dataset import Dataset
from stages.common.frame_skip import frame_indices
from stages.tokenize.store import TokenStore
from stages.tokenize.tokenizer import load_tokenizer
from stages.train_wm.data import ClipSampler, load_episodes, split_episodes
from stages.train_wm.evaluate import horizon_eval, real_images, rollout_starts
from stages.train_wm.model import WorldModelNet
from stages.train_wm.rollout import WorldModel, load_net, save_world_model
from stages.train_wm.train import train_world_model


def main() -> None:
    torch.set_num_threads(1)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("collect", type=Path)
    ap.add_argument("tokenize", type=Path)
    ap.add_argument("overrides", type=json.loads, help="train_wm config overrides as JSON")
    ap.add_argument("--save", type=Path, default=None, help="write the trained action WM checkpoint here")
    ap.add_argument("--load", type=Path, default=None,
                    help="evaluate this action WM checkpoint (e.g. a train_wm artifact's action_wm.pt) instead of "
                         "training one; the overrides still pick the data (frame_skip, seed)")
    args = ap.parse_args()
    collect, tok_dir, overrides = args.collect, args.tokenize, args.overrides
    cfg = W.Config(**overrides)
    torch.manual_seed(cfg.seed)
    eps = load_episodes(collect, tok_dir, frame_skip=cfg.frame_skip)
    held = set(json.loads((tok_dir / "split.json").read_text())["heldout"])
    train, heldout, ood = split_episodes(eps, held, cfg.holdout_fraction, cfg.seed)
    store = TokenStore(tok_dir)
    if args.load:
        evaluate(load_net(args.load), cfg, collect, tok_dir, heldout, ood)
        return
    net = WorldModelNet(W.model_spec(cfg, "action", 2**store.bits, tuple(store.grid)))
    net.set_action_stats(torch.from_numpy(np.concatenate([e.actions for e in train])))
    sampler = ClipSampler(train, cfg.window, {e.instruction: np.zeros(384, np.float32) for e in eps}, cfg.seed)
    t0 = time.time()
    r = train_world_model(net, sampler, steps=cfg.action_steps, batch_size=cfg.batch_size, lr=cfg.lr,
                          weight_decay=cfg.weight_decay, done_weight=cfg.done_weight, done_kind=cfg.done_loss,
                          seed=cfg.seed, device="cpu", changed_weight=cfg.changed_weight,
                          done_balance=cfg.done_balance)
    print(overrides, f"{len(train)} train episodes, train s {time.time() - t0:.0f}",
          {k: round(v, 3) for k, v in r["final"].items()}, flush=True)
    if args.save:
        save_world_model(net, args.save, {"decode_steps": cfg.decode_steps, "temperature": cfg.temperature})
    evaluate(net, cfg, collect, tok_dir, heldout, ood)


def evaluate(net, cfg, collect: Path, tok_dir: Path, heldout: list, ood: list) -> None:
    """Open-loop metrics at horizons 1, 5, 15 on the held-out IND and (up to 6) OOD episodes."""
    wm = WorldModel(net, cfg.decode_steps, 0.0)
    tok, ds = load_tokenizer(tok_dir, "cpu"), Dataset(collect)
    for name, split in (("ind", heldout), ("ood", ood[:6])):
        starts = rollout_starts(split, 15, 6, np.random.default_rng(0))
        images = {}
        for i in sorted({i for i, _ in starts}):
            ep = ds.load(split[i].episode_id)
            keep = frame_indices(len(ep.action), cfg.frame_skip)
            images[split[i].episode_id] = real_images(tok, ep.third[keep], ep.wrist[keep])
        m, _ = horizon_eval(wm, tok, split, images, starts, {}, "cpu", True)
        for h in (1, 5, 15):
            g = lambda row, key: m[f"h{h}/{row}/{key}"]  # noqa: E731
            print(f"  {name} h{h}: PSNR wm {g('wm', 'psnr'):.2f} copy {g('copy_last', 'psnr'):.2f} "
                  f"shuffled {g('shuffled_actions', 'psnr'):.2f} tokenizer {g('tokenizer', 'psnr'):.2f} | "
                  f"LPIPS wm {g('wm', 'lpips'):.3f} copy {g('copy_last', 'lpips'):.3f} | "
                  f"token acc wm {g('wm', 'token_acc'):.3f} copy {g('copy_last', 'token_acc'):.3f} | "
                  f"true-vs-shuffled L1 {m[f'h{h}/true_vs_shuffled_pixel_l1']:.4f} | starts {m['starts']}", flush=True)


if __name__ == "__main__":
    main()
