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

    # a tokenize artifact no world model was trained on (another grid): no train_wm argument (its
    # default config, instructions encoded here); --tokenizer adds decoded PSNR and a strip per model
    PYTHONPATH=. .venv/bin/python scripts/wm_size_probe.py export <collect> <tokenize> --out .probe/d16.pt
    python scripts/wm_size_probe.py train .probe/d16.pt '{...}' --tokenizer <tokenize> --device cuda --save-dir $OUT

    # here: another collect (e.g. a re-collection with another trajectory mix) tokenized with an existing
    # tokenizer, as the tokenize stage encodes and splits; then export from that folder; train two models
    # that differ only in one kind of training data (the evaluation keeps every kind)
    PYTHONPATH=. .venv/bin/python scripts/wm_size_probe.py encode <collect2> <tokenize> --out .probe/enc
    PYTHONPATH=. .venv/bin/python scripts/wm_size_probe.py export <collect2> .probe/enc --out .probe/d.pt
    python scripts/wm_size_probe.py train .probe/d.pt '{}' [--exclude-kinds grasp_miss] --save-dir DIR

    # here: a folder that loads as a train_wm artifact (proprioception head trained with its recipe)
    PYTHONPATH=. .venv/bin/python scripts/wm_size_probe.py assemble .probe/d16.pt --net m0.pt \
        --tokenizer <tokenize> --out DIR     # then: scripts/replay_imagined.py <collect> <tokenize> DIR <sft> ...

Each saved checkpoint is the stage's format (``save_world_model``): ``scripts/replay_imagined.py
... --wm-net FILE`` imagines in it (the train_wm artifact's proprioception head and decoding stay),
``scripts/wm_ablation.py <collect> <tokenize> '{}' --load FILE`` decodes it for PSNR / LPIPS.

Metrics (held-out IND episodes and OOD episodes): teacher-forced token cross-entropy and accuracy
of hidden tokens (the training loss's masking, fixed seed), open-loop token accuracy at horizons
1, 5, 15 from real start frames under the recorded actions (next to copy-last), done-head AUROC
on real sequences and each failure kind's false-alarm rate at train_wm's done_threshold (the stage's metrics).
``imagined_success``: every held-out / OOD episode imagined open loop from its first frame under its
recorded actions, imagined done against the real outcome, per trajectory kind (near-misses included).
"""
from __future__ import annotations

import argparse
import gzip
import io
import json
import time
from pathlib import Path

import numpy as np
import torch


def export(args) -> None:
    import stages.train_wm as W
    from stages.tokenize.store import TokenStore
    from stages.train_wm.data import load_episodes, split_episodes

    if args.play_sft and args.train_wm is None:
        raise ValueError("--play-sft needs the train_wm artifact (its split and instruction embeddings)")
    if args.train_wm is not None:
        wm_config = json.loads((args.train_wm / "manifest.json").read_text())["key_inputs"]["config"]
    else:  # a tokenize artifact no world model was trained on (another token grid): train_wm's defaults
        wm_config = W.Config().model_dump(mode="json")
    cfg = W.Config(**wm_config)  # the artifact's own config: frame skip, split seed (and the defaults of `train`)
    episodes = load_episodes(args.collect, args.tokenize, frame_skip=cfg.frame_skip)
    split = json.loads((args.tokenize / "split.json").read_text())
    train, held, ood = split_episodes(episodes, set(split.get("heldout", [])), cfg.holdout_fraction, cfg.seed)
    store = TokenStore(args.tokenize)
    if args.train_wm is not None:
        text = {k: np.asarray(v, np.float32)
                for k, v in json.loads((args.train_wm / "text_embeddings.json").read_text()).items()}
    else:
        from stages.common.text_encoder import encode_texts

        instructions = sorted({e.instruction for e in episodes})
        text = dict(zip(instructions, (np.asarray(v, np.float32) for v in encode_texts(instructions))))
    play = sft_play(args, cfg.frame_skip) if args.play_sft else []
    for ep in episodes + play:
        ep.tokens = ep.tokens.astype(np.int16)  # (T+1, N): ids < 2^bits <= 2^15, a quarter of the file; int64 again on load
    args.out.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save({"train": train, "heldout": held, "ood": ood, "play": play, "text_emb": text, "wm_config": wm_config,
                "vocab": 2**store.bits, "grid": tuple(store.grid)}, buf)
    args.out.write_bytes(gzip.compress(buf.getvalue(), compresslevel=6))  # the GPU machine takes 64 MiB in all
    print(f"{len(train)} train / {len(held)} held-out IND / {len(ood)} OOD / {len(play)} play episodes -> {args.out} "
          f"({args.out.stat().st_size / 2**20:.1f} MiB)")


def encode(args) -> None:
    """A folder that reads as a tokenize artifact of ``args.collect`` (``tokens.npy``, ``index.json``,
    ``split.json``, ``tokenizer.pt``) made with another collect's tokenizer, not trained again: the
    tokenize stage's own encoding and held-out rule (its seed and fraction), so a re-collected store
    (another trajectory mix) is compared under one fixed tokenizer."""
    import shutil

    from stages.tokenize import Config as TokConfig
    from stages.tokenize import encode_all, heldout_split, open_dataset, write_split
    from stages.tokenize.tokenizer import CHECKPOINT, load_tokenizer

    tcfg = TokConfig(**json.loads((args.tokenize / "manifest.json").read_text())["key_inputs"]["config"])
    ds = open_dataset(args.collect)
    args.out.mkdir(parents=True, exist_ok=True)
    train_eps, held = heldout_split([e for e in ds.episodes if e.split == "ind"], tcfg.holdout_fraction,
                                    np.random.default_rng(tcfg.seed))
    write_split(args.out, train_eps, held)
    shutil.copyfile(args.tokenize / CHECKPOINT, args.out / CHECKPOINT)
    t0 = time.perf_counter()
    usage = encode_all(args.out, ds, load_tokenizer(args.tokenize, "cpu"), tcfg.encode_batch)
    (args.out / "encoded.json").write_text(json.dumps({"collect": str(args.collect), "tokenizer": str(args.tokenize),
                                                        **usage}, indent=1) + "\n")
    print(f"{args.out}: {usage['episodes']} episodes, {usage['frames']} frames, {len(held)} IND held out, "
          f"{time.perf_counter() - t0:.0f} s")


def load_data(path: Path) -> dict:
    """An exported file (gzip-compressed; older exports are plain torch files)."""
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        raw = gzip.decompress(raw)
    return torch.load(io.BytesIO(raw), weights_only=False)


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
    obs_fn = ObservationFn.for_policy(load_tokenizer(args.tokenize, "cpu"),
                                      json.loads((args.train_wm / "text_embeddings.json").read_text()),
                                      read_policy_json(args.play_sft))
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
def open_loop_acc(wm, episodes: list, horizons=(1, 5, 15), per_episode: int = 4, tok=None) -> dict[str, float]:
    """Open-loop token accuracy (fraction of the frame's tokens right) and copy-last's, per horizon; with
    the tokenizer ``tok`` also the PSNR of the decoded prediction against the real frame's tokens decoded
    (whole observation and third view alone), a measure that compares models of different token grids."""
    from stages.train_wm.evaluate import decoded, open_loop, rollout_starts, true_actions

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
        if tok is not None:
            grid = wm.spec.grid
            ref = decoded(tok, real[:, h - 1].view(-1, *grid)).clamp(0, 1)  # (K, 3, S, 2S)
            for name, toks in (("wm", pred[:, h - 1]), ("copy", first)):
                img = decoded(tok, toks.reshape(-1, *grid)).clamp(0, 1)
                out[f"h{h}/{name}/psnr"] = psnr(img, ref)
                out[f"h{h}/{name}/psnr_third"] = psnr(img[..., : ref.shape[-2]], ref[..., : ref.shape[-2]])
    return out


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean per-image PSNR (dB) of (K, 3, H, W) images in [0, 1]; identical images (+inf) left out, as
    train_wm's evaluation does."""
    from stages.common import image_metrics

    v = image_metrics.psnr(img, ref).double()
    v = v[torch.isfinite(v)]
    return float(v.mean()) if len(v) else float("nan")


@torch.no_grad()
def imagined_success(wm, episodes: list, theta: float, batch: int = 128) -> dict:
    """Every episode imagined open loop from its first frame under all of its recorded actions: imagined
    done (the done head reaches ``theta`` at some step) against the episode's real outcome (the simulator's
    success at some frame). Near-misses and suboptimal demonstrations included, so this is the precision
    of the world model's imagined successes on the planner's actions, comparable across token grids."""
    h, w = wm.spec.grid
    imagined, real, kinds = [], [], []
    for b0 in range(0, len(episodes), batch):
        eps = episodes[b0 : b0 + batch]
        t_max = max(e.length for e in eps)
        acts = torch.zeros(len(eps), t_max, 7)  # (B, T, 7), zero past an episode's end (its steps are not read)
        for j, e in enumerate(eps):
            acts[j, : e.length] = torch.from_numpy(e.actions)
        lengths = torch.tensor([e.length for e in eps])
        roll = wm.rollout(len(eps))
        roll.reset(torch.stack([torch.from_numpy(e.tokens[0]) for e in eps]).view(len(eps), h, w))
        peak = torch.zeros(len(eps))
        for t in range(t_max):
            p = roll.step(acts[:, t]).done_prob.float().cpu()
            peak = torch.where(t < lengths, torch.maximum(peak, p), peak)
        imagined += (peak >= theta).tolist()
        real += [bool(e.done.max() > 0) for e in eps]
        kinds += [e.kind for e in eps]
    imagined, real = np.array(imagined), np.array(real)
    out = {"episodes": len(real), "real_success": int(real.sum()), "imagined_done": int(imagined.sum()),
           "both": int((imagined & real).sum()),
           "precision": float((imagined & real).sum() / imagined.sum()) if imagined.sum() else float("nan"),
           "recall": float((imagined & real).sum() / real.sum()) if real.sum() else float("nan")}
    for kind in sorted(set(kinds)):
        m = np.array([k == kind for k in kinds])
        out[f"{kind}/imagined_done"] = f"{int(imagined[m].sum())}/{int(m.sum())} (real {int(real[m].sum())})"
    return out


def evaluate(net, data: dict, cfg, device: str, tok=None) -> dict:
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
                      "open_loop_token_acc": open_loop_acc(wm, eps, tok=tok),
                      "imagined_success": imagined_success(wm, eps, cfg.done_threshold),
                      "done": {k: v for k, v in done_head_eval(wm, eps, cfg.done_threshold, data["text_emb"]).items()
                               if k in ("auroc", "precision", "recall")},
                      **{kind: false_alarm_rate(wm, [e for e in eps if e.kind == kind], cfg.done_threshold, data["text_emb"])
                         for kind in FAILURE_KINDS}}
    return out


def train(args) -> None:
    import stages.train_wm as W
    from stages.train_wm.model import WorldModelNet
    from stages.train_wm.rollout import load_net

    data = load_data(args.data)
    if (args.finetune or args.with_play) and not data.get("play"):
        raise ValueError(f"--finetune / --with-play need play episodes: {args.data} was exported without --play-sft")
    for split in ("train", "heldout", "ood", "play"):
        for ep in data.get(split, []):
            ep.tokens = ep.tokens.astype(np.int64)
    dev = args.device
    args.tok = None
    if args.tokenizer is not None:
        from stages.tokenize.tokenizer import load_tokenizer

        args.tok = load_tokenizer(args.tokenizer, dev)
        if tuple(args.tok.grid) != tuple(data["grid"]):
            raise ValueError(f"--tokenizer {args.tokenizer} has grid {tuple(args.tok.grid)}, the data {tuple(data['grid'])}")
    results = {}
    if args.save_dir:
        args.save_dir.mkdir(parents=True, exist_ok=True)
    if args.baseline:
        net = load_net(args.baseline, dev)
        t0 = time.perf_counter()
        results["baseline"] = {"params": sum(p.numel() for p in net.parameters()),
                               "eval": evaluate(net, data, W.Config(**data["wm_config"]), dev, args.tok)}
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
        clips = [e for e in W.training_episodes(data["train"], "action", cfg.done_negatives)
                 if e.kind not in args.exclude_kinds] + data["play"] * args.with_play
        fit(f"m{i}", net, cfg, clips, cfg.action_steps, cfg.lr, cfg.seed, cfg.seed, data, args, results,
            {"overrides": overrides, "with_play": args.with_play, "exclude_kinds": args.exclude_kinds,
             "train_episodes": len(clips), "params": sum(p.numel() for p in net.parameters())})


def fit(name: str, net, cfg, clips: list, steps: int, lr: float, sampler_seed: int, seed: int, data: dict, args,
        results: dict, facts: dict) -> None:
    """Train ``net`` on ``clips`` with train_wm's losses (``cfg``), evaluate it, record, print and save it."""
    from stages.train_wm.data import ClipSampler
    from stages.train_wm.rollout import save_world_model
    from stages.train_wm.train import train_world_model

    r = train_world_model(net.to(args.device), ClipSampler(clips, cfg.window, data["text_emb"], sampler_seed), steps=steps,
                          batch_size=cfg.batch_size, lr=lr, weight_decay=cfg.weight_decay, done_weight=cfg.done_weight,
                          done_kind=cfg.done_loss, seed=seed, device=args.device, changed_weight=cfg.changed_weight,
                          done_balance=cfg.done_balance, context_noise=cfg.context_noise, self_context=cfg.self_context,
                          log=_stdout_log(), desc=name)
    results[name] = {**facts, "train_seconds": r["seconds"], "final": r["final"],
                     "eval": evaluate(net, data, cfg, args.device, args.tok)}
    if args.tok is not None and args.save_dir:
        strip(net, data, cfg, args.tok, args.save_dir / f"{name}_strip.png")
    print(name, json.dumps(results[name]), flush=True)
    if args.save_dir:
        save_world_model(net.cpu(), args.save_dir / f"{name}.pt",
                         {"decode_steps": cfg.decode_steps, "temperature": cfg.temperature})
        (args.save_dir / "results.json").write_text(json.dumps(results, indent=1) + "\n")


def _stdout_log():
    """A logger that prints train_world_model's progress lines (every tenth of the steps) with the time."""
    import logging
    import sys

    log = logging.getLogger("wm_size_probe")
    if not log.handlers:
        h = logging.StreamHandler(sys.stdout)
        h.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S"))
        log.addHandler(h)
        log.setLevel(logging.INFO)
        log.propagate = False
    return log


def assemble(args) -> None:
    """A folder that loads as a train_wm artifact's action world model (``load_world_model``): the given
    checkpoint as ``action_wm.pt``, a proprioception head trained here with train_wm's recipe on the
    export's training episodes and tokenizer, and the export's instruction embeddings. With it the
    policy checks (``scripts/replay_imagined.py``) imagine in a model trained elsewhere, on any grid."""
    import shutil

    import stages.train_wm as W
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.proprio import CHECKPOINT, ProprioHead, save_head, train_proprio_head, transitions
    from stages.train_wm.rollout import CHECKPOINTS, TEXT_EMBEDDINGS, load_net

    data = load_data(args.data)
    tok = load_tokenizer(args.tokenizer, "cpu")
    net = load_net(args.net)
    if tuple(net.spec.grid) != tuple(tok.grid) or tuple(data["grid"]) != tuple(tok.grid):
        raise ValueError(f"grids differ: checkpoint {tuple(net.spec.grid)}, tokenizer {tuple(tok.grid)}, "
                         f"export {tuple(data['grid'])}")
    cfg = W.Config(**data["wm_config"])
    for ep in data["train"]:
        ep.tokens = ep.tokens.astype(np.int64)
    torch.manual_seed(cfg.seed)
    head = ProprioHead(tok.bits, tok.grid)
    codes = lambda t: tok.codes(torch.from_numpy(t.reshape(len(t), *tok.grid)))  # noqa: E731  (n, N) -> (n, bits, h, w)
    r = train_proprio_head(head, transitions(data["train"], codes), steps=cfg.proprio_steps,
                           batch_size=cfg.proprio_batch_size, lr=cfg.proprio_lr, seed=cfg.seed, device="cpu")
    args.out.mkdir(parents=True, exist_ok=True)
    save_head(head, args.out / CHECKPOINT)
    shutil.copyfile(args.net, args.out / CHECKPOINTS["action"])
    (args.out / TEXT_EMBEDDINGS).write_text(json.dumps({k: np.asarray(v).tolist() for k, v in data["text_emb"].items()}) + "\n")
    print(f"{args.out}: {CHECKPOINTS['action']} from {args.net}, {CHECKPOINT} ({r['seconds']:.0f} s, final loss "
          f"{r['final']:.4f}), {TEXT_EMBEDDINGS}")


@torch.no_grad()
def strip(net, data: dict, cfg, tok, path: Path, envs: int = 4, steps: int = 24, every: int = 3) -> None:
    """Third view of ``envs`` held-out IND (else OOD) episodes (successful ones first): imagined open loop from the
    first frame under the recorded actions, over the real frame's tokens decoded, every ``every`` steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stages.train_wm.evaluate import decoded, open_loop, true_actions
    from stages.train_wm.rollout import WorldModel

    eps = sorted(data["heldout"] or data["ood"], key=lambda e: (e.done.max() <= 0, e.episode_id))
    steps = min(steps, max((e.length for e in eps), default=0))
    eps = [e for e in eps if e.length >= steps][:envs]
    if not eps or steps < 1:
        return
    every = max(1, min(every, steps // 4))
    wm = WorldModel(net.eval(), cfg.decode_steps, 0.0)
    starts = [(i, 0) for i in range(len(eps))]
    pred = open_loop(wm, eps, starts, steps, actions=true_actions(eps, starts, steps)).cpu()  # (E, steps, N)
    shown = list(range(0, steps + 1, every))
    fig, axes = plt.subplots(2 * len(eps), len(shown), figsize=(1.2 * len(shown), 2.5 * len(eps)), squeeze=False)
    for j, e in enumerate(eps):
        real = decoded(tok, torch.from_numpy(e.tokens[: steps + 1]).view(-1, *wm.spec.grid)).clamp(0, 1)
        imag = torch.cat([real[:1], decoded(tok, pred[j].view(-1, *wm.spec.grid)).clamp(0, 1)])
        size = real.shape[-2]
        for c, t in enumerate(shown):
            for r, (frames, label) in enumerate(((imag, "imagined"), (real, "real"))):
                ax = axes[2 * j + r, c]
                ax.imshow(frames[t, :, :, :size].permute(1, 2, 0).numpy())
                ax.set_xticks([]), ax.set_yticks([])
                if c == 0:
                    ax.set_ylabel(f"{label}\n{e.kind}", fontsize=6)
                if j == 0 and r == 0:
                    ax.set_title(f"t={t}", fontsize=6)
    fig.suptitle(f"open loop, recorded actions, grid {tuple(wm.spec.grid)}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="write the action WM's training data of a store to one file")
    e.add_argument("collect", type=Path)
    e.add_argument("tokenize", type=Path)
    e.add_argument("train_wm", type=Path, nargs="?", default=None,
                   help="the train_wm artifact (its config and instruction embeddings); without it train_wm's "
                        "default config and freshly encoded instructions, e.g. for a tokenize artifact of another grid")
    e.add_argument("--out", type=Path, required=True)
    e.add_argument("--play-sft", type=Path, default=None,
                   help="an sft artifact: also record its policy's play as the wm_play stage does (for --finetune)")
    e.add_argument("--play-episodes", type=int, default=384, help="play episodes (wm_play.episodes)")
    e.add_argument("--play-steps", type=int, default=75, help="policy steps per play episode at most (wm_play.max_episode_steps)")
    c = sub.add_parser("encode", help="tokenize a collect artifact with another collect's tokenizer (no training)")
    c.add_argument("collect", type=Path)
    c.add_argument("tokenize", type=Path, help="the tokenize artifact whose tokenizer (config: seed, held-out fraction) is used")
    c.add_argument("--out", type=Path, required=True, help="a folder that then reads as a tokenize artifact of the collect")
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
    t.add_argument("--exclude-kinds", nargs="*", default=[],
                   help="trajectory kinds left out of the training clips of models trained from scratch (e.g. grasp_miss); "
                        "the evaluation keeps every kind")
    t.add_argument("--device", default="cpu")
    t.add_argument("--tokenizer", type=Path, default=None,
                   help="the tokenize artifact (or a folder with its tokenizer.pt) of the exported tokens: also "
                        "decoded open-loop PSNR, and a frame strip per model in --save-dir")
    t.add_argument("--save-dir", type=Path, default=None, help="write m<i>.pt per trained model and results.json here")
    a = sub.add_parser("assemble", help="a folder that loads as train_wm's action world model, from a checkpoint")
    a.add_argument("data", type=Path, help="the exported file the checkpoint was trained on")
    a.add_argument("--net", type=Path, required=True, help="an action world-model checkpoint (m<i>.pt of train)")
    a.add_argument("--tokenizer", type=Path, required=True, help="the tokenize artifact of the export")
    a.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if args.cmd != "encode" and (args.cmd != "train" or args.device == "cpu"):
        torch.set_num_threads(1)  # models side by side on the 2 cores; encode runs alone, on torch's default
    {"export": export, "encode": encode, "train": train, "assemble": assemble}[args.cmd](args)


if __name__ == "__main__":
    main()
