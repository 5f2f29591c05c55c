"""Does a better-trained or larger action world model imagine more faithfully? Train the action WM
with other sizes and budgets on a GPU, from the store's own episodes, and compare it with the
train_wm artifact's on the same data.

The collect artifact (MCAP frames) is too large to send to a lent GPU machine, so this works in
two steps:

    # here: the action WM's training data as the train_wm stage sees it (tokens, composed actions,
    # done labels, proprioception; its train / held-out IND / OOD split; the artifact's config),
    # and with --play-sft the SFT policy's play as the wm_play stage records it (seed 0's seeds)
    PYTHONPATH=. .venv/bin/python scripts/wm_size_probe.py export <collect> <tokenize> <train_wm> \
        --out .probe/data.pt [--play-sft <sft>]

    # on the GPU: train one action WM per JSON override set (over the artifact's train_wm config),
    # as the stage trains it [also on the play: --with-play 2]; fine-tune saved checkpoints on the
    # training episodes + play as the wm_play stage does [--finetune FILE --finetune-overrides JSON];
    # print teacher-forced and open-loop metrics, next to the artifact's model with --baseline
    python scripts/wm_size_probe.py train .probe/data.pt '{"batch_size": 32, "action_steps": 6000}' ... \
        --baseline <train_wm>/action_wm.pt --device cuda --save-dir $OUT

Each saved checkpoint is the stage's format (``save_world_model``): ``scripts/replay_imagined.py
... --wm-net FILE`` imagines in it (the train_wm artifact's proprioception head and decoding stay),
``scripts/wm_ablation.py <collect> <tokenize> '{}' --load FILE`` decodes it for PSNR / LPIPS.

Metrics (held-out IND episodes and OOD episodes): teacher-forced token cross-entropy and accuracy
of hidden tokens (the training loss's masking, fixed seed), open-loop token accuracy at horizons
1, 5, 15 from real start frames under the recorded actions (next to copy-last), done-head AUROC
on real sequences and the near-miss false-alarm rate at train_wm's done_threshold (the stage's metrics).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def export(args) -> None:
    import stages.train_wm as W
    from stages.tokenize.store import TokenStore
    from stages.train_wm.data import load_episodes, split_episodes

    wm_config = json.loads((args.train_wm / "manifest.json").read_text())["key_inputs"]["config"]
    cfg = W.Config(**wm_config)  # the artifact's own config: frame skip, split seed (and the defaults of `train`)
    episodes = load_episodes(args.collect, args.tokenize, frame_skip=cfg.frame_skip)
    split = json.loads((args.tokenize / "split.json").read_text())
    train, held, ood = split_episodes(episodes, set(split.get("heldout", [])), cfg.holdout_fraction, cfg.seed)
    store = TokenStore(args.tokenize)
    text = {k: np.asarray(v, np.float32) for k, v in json.loads((args.train_wm / "text_embeddings.json").read_text()).items()}
    play = sft_play(args, cfg.frame_skip) if args.play_sft else []
    for ep in episodes + play:
        ep.tokens = ep.tokens.astype(np.int16)  # (T+1, N): ids < 2^bits <= 2^15, a quarter of the file; int64 again on load
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"train": train, "heldout": held, "ood": ood, "play": play, "text_emb": text, "wm_config": wm_config,
                "vocab": 2**store.bits, "grid": tuple(store.grid)}, args.out)
    print(f"{len(train)} train / {len(held)} held-out IND / {len(ood)} OOD / {len(play)} play episodes -> {args.out} "
          f"({args.out.stat().st_size / 2**20:.1f} MiB)")


def sft_play(args, frame_skip: int) -> list:
    """The wm_play stage's play (its defaults: seed 0's play seeds, 75 policy steps, round-robin over the
    IND training environments of the policy's tasks): the SFT policy's own episodes, failures kept."""
    from stages.common.environments import pick_environments, training_environments
    from stages.common.sim_env import sim_over
    from stages.goals.environments import list_environments
    from stages.sft import read_policy_json
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, load_policy
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.wm_play import Config as PlayConfig
    from stages.wm_play.play import PLAY_SEED, play_episodes

    pc = PlayConfig(episodes=args.play_episodes, max_episode_steps=args.play_steps)
    split = json.loads((args.train_wm / "split.json").read_text())
    tasks = list(read_policy_json(args.play_sft)["tasks"])
    picked = pick_environments(training_environments(list_environments(args.collect), split["train"], tasks), pc.episodes)
    obs_fn = ObservationFn(load_tokenizer(args.tokenize, "cpu"),
                           json.loads((args.train_wm / "text_embeddings.json").read_text()))
    sim, specs = sim_over(args.collect, obs_fn, picked, max_steps=pc.max_episode_steps, frame_skip=frame_skip, seed=pc.seed)
    policy = load_policy(args.play_sft / POLICY_FILE, "cpu")
    policy.set_training_mode(False)
    t0 = time.perf_counter()
    try:
        play = play_episodes(policy, sim, specs, [PLAY_SEED + 1000 * pc.seed + i for i in range(len(specs))],
                             pc.max_episode_steps)
    finally:
        sim.close()
    print(f"play: {len(play)} episodes, {sum(p.done[-1] > 0 for p in play)} successes, {time.perf_counter() - t0:.0f} s")
    return play


@torch.no_grad()
def teacher_forced(net, episodes: list, text_emb: dict, cfg, device: str, batches: int = 40) -> dict[str, float]:
    """Mean token CE / accuracy of hidden tokens and done loss over ``batches`` fixed-seed clips."""
    from stages.train_wm.data import ClipSampler
    from stages.train_wm.train import losses

    sampler, gen = ClipSampler(episodes, cfg.window, text_emb, 1234), torch.Generator().manual_seed(1234)
    out = {"ce": 0.0, "acc": 0.0, "done": 0.0}
    for _ in range(batches):
        r = losses(net, sampler.sample(16, device), gen, cfg.done_loss, cfg.changed_weight, cfg.done_balance)
        for k in out:
            out[k] += float(r[k]) / batches
    return out


@torch.no_grad()
def open_loop_acc(wm, episodes: list, horizons=(1, 5, 15), per_episode: int = 4) -> dict[str, float]:
    """Open-loop token accuracy (fraction of the frame's tokens right) and copy-last's, per horizon."""
    from stages.train_wm.evaluate import open_loop, rollout_starts, true_actions

    longest = max((e.length for e in episodes), default=0)
    horizons = [h for h in horizons if h <= longest]  # short (toy) episodes: the horizons they have
    starts = rollout_starts(episodes, max(horizons), per_episode, np.random.default_rng(0)) if horizons else []
    if not starts:
        return {"starts": 0}
    hmax = max(horizons)
    pred = open_loop(wm, episodes, starts, hmax, actions=true_actions(episodes, starts, hmax)).cpu()  # (K, hmax, N)
    real = torch.stack([torch.from_numpy(episodes[i].tokens[s + 1 : s + 1 + hmax]) for i, s in starts])  # (K, hmax, N)
    first = torch.stack([torch.from_numpy(episodes[i].tokens[s]) for i, s in starts])  # (K, N)
    out = {"starts": len(starts)}
    for h in horizons:
        out[f"h{h}/wm"] = float((pred[:, h - 1] == real[:, h - 1]).float().mean())
        out[f"h{h}/copy"] = float((first == real[:, h - 1]).float().mean())
    return out


def evaluate(net, data: dict, cfg, device: str) -> dict:
    """The metrics above on the held-out IND and the OOD episodes (a split without episodes is left out)."""
    from stages.collect.plans import FAILURE_KINDS
    from stages.train_wm.evaluate import done_head_eval, false_alarm_rate
    from stages.train_wm.rollout import WorldModel

    wm = WorldModel(net.eval(), cfg.decode_steps, 0.0)
    out = {}
    for split in ("heldout", "ood"):
        eps = data[split]
        if not eps:
            continue
        out[split] = {"teacher_forced": teacher_forced(net, eps, data["text_emb"], cfg, device),
                      "open_loop_token_acc": open_loop_acc(wm, eps),
                      "done": {k: v for k, v in done_head_eval(wm, eps, cfg.done_threshold, data["text_emb"]).items()
                               if k in ("auroc", "precision", "recall")},
                      "near_miss": false_alarm_rate(wm, [e for e in eps if e.kind in FAILURE_KINDS], cfg.done_threshold,
                                                    data["text_emb"])}
    return out


def train(args) -> None:
    import stages.train_wm as W
    from stages.train_wm.model import WorldModelNet
    from stages.train_wm.rollout import load_net

    data = torch.load(args.data, weights_only=False)
    if (args.finetune or args.with_play) and not data.get("play"):
        raise ValueError(f"--finetune / --with-play need play episodes: {args.data} was exported without --play-sft")
    for split in ("train", "heldout", "ood", "play"):
        for ep in data.get(split, []):
            ep.tokens = ep.tokens.astype(np.int64)
    dev = args.device
    results = {}
    if args.save_dir:
        args.save_dir.mkdir(parents=True, exist_ok=True)
    if args.baseline:
        net = load_net(args.baseline, dev)
        t0 = time.perf_counter()
        results["baseline"] = {"params": sum(p.numel() for p in net.parameters()),
                               "eval": evaluate(net, data, W.Config(**data["wm_config"]), dev)}
        print("baseline", json.dumps(results["baseline"]), f"({time.perf_counter() - t0:.0f} s)", flush=True)
        if args.save_dir:
            (args.save_dir / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    for i, path in enumerate(args.finetune):
        cfg = W.Config(**{**data["wm_config"], **(args.finetune_overrides[i] if i < len(args.finetune_overrides) else {})})
        fit(f"{path.stem}_play", load_net(path, dev), cfg, data["train"] + data["play"] * args.play_weight,
            args.finetune_steps, args.finetune_lr, cfg.seed + 99, cfg.seed + 7, data, args, results,
            {"finetuned": str(path), "batch_size": cfg.batch_size, "play": len(data["play"])})
    for i, overrides in enumerate(args.overrides):
        cfg = W.Config(**{**data["wm_config"], **overrides})
        torch.manual_seed(cfg.seed)
        net = WorldModelNet(W.model_spec(cfg, "action", data["vocab"], data["grid"])).to(dev)
        net.set_action_stats(torch.from_numpy(np.concatenate([e.actions for e in data["train"]])).to(dev))
        clips = W.training_episodes(data["train"], "action", cfg.done_negatives) + data["play"] * args.with_play
        fit(f"m{i}", net, cfg, clips, cfg.action_steps, cfg.lr, cfg.seed, cfg.seed, data, args, results,
            {"overrides": overrides, "with_play": args.with_play, "params": sum(p.numel() for p in net.parameters())})


def fit(name: str, net, cfg, clips: list, steps: int, lr: float, sampler_seed: int, seed: int, data: dict, args,
        results: dict, facts: dict) -> None:
    """Train ``net`` on ``clips`` with train_wm's losses (``cfg``), evaluate it, record, print and save it."""
    from stages.train_wm.data import ClipSampler
    from stages.train_wm.rollout import save_world_model
    from stages.train_wm.train import train_world_model

    r = train_world_model(net.to(args.device), ClipSampler(clips, cfg.window, data["text_emb"], sampler_seed), steps=steps,
                          batch_size=cfg.batch_size, lr=lr, weight_decay=cfg.weight_decay, done_weight=cfg.done_weight,
                          done_kind=cfg.done_loss, seed=seed, device=args.device, changed_weight=cfg.changed_weight,
                          done_balance=cfg.done_balance, context_noise=cfg.context_noise, self_context=cfg.self_context)
    results[name] = {**facts, "train_seconds": r["seconds"], "final": r["final"],
                     "eval": evaluate(net, data, cfg, args.device)}
    print(name, json.dumps(results[name]), flush=True)
    if args.save_dir:
        save_world_model(net.cpu(), args.save_dir / f"{name}.pt",
                         {"decode_steps": cfg.decode_steps, "temperature": cfg.temperature})
        (args.save_dir / "results.json").write_text(json.dumps(results, indent=1) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="write the action WM's training data of a store to one file")
    e.add_argument("collect", type=Path)
    e.add_argument("tokenize", type=Path)
    e.add_argument("train_wm", type=Path, help="the train_wm artifact (its instruction embeddings)")
    e.add_argument("--out", type=Path, required=True)
    e.add_argument("--play-sft", type=Path, default=None,
                   help="an sft artifact: also record its policy's play as the wm_play stage does (for --finetune)")
    e.add_argument("--play-episodes", type=int, default=384, help="play episodes (wm_play.episodes)")
    e.add_argument("--play-steps", type=int, default=75, help="policy steps per play episode at most (wm_play.max_episode_steps)")
    t = sub.add_parser("train", help="train and evaluate action WMs on an exported file")
    t.add_argument("data", type=Path)
    t.add_argument("overrides", type=json.loads, nargs="*",
                   help="train_wm Config overrides of the exported artifact's config, one JSON object per model")
    t.add_argument("--baseline", type=Path, default=None, help="an action_wm.pt to evaluate on the same data first")
    t.add_argument("--finetune", type=Path, nargs="*", default=[],
                   help="checkpoints to fine-tune on the training episodes plus the exported play (listed --play-weight "
                        "times) as the wm_play stage does, --finetune-steps steps at --finetune-lr, each with the "
                        "--finetune-overrides object at the same position (its batch size; default train_wm's)")
    t.add_argument("--finetune-overrides", type=json.loads, nargs="*", default=[])
    t.add_argument("--finetune-steps", type=int, default=2000)
    t.add_argument("--finetune-lr", type=float, default=3e-4)
    t.add_argument("--play-weight", type=int, default=2)
    t.add_argument("--with-play", type=int, default=0,
                   help="models trained from scratch also train on the exported play, listed this many times")
    t.add_argument("--device", default="cpu")
    t.add_argument("--save-dir", type=Path, default=None, help="write m<i>.pt per trained model and results.json here")
    args = ap.parse_args()
    if args.cmd == "export" or args.device == "cpu":
        torch.set_num_threads(1)
    export(args) if args.cmd == "export" else train(args)


if __name__ == "__main__":
    main()
