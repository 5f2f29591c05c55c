"""train_wm: the action world model and the text world model, with done heads, and their evaluation.

Inputs:
    collect -- episodes (``stages.collect.dataset.Dataset``): actions (T, 7) delta-EE, the simulator's
    success flag per frame (done labels: done[t] = success[t]), instruction, split ('ind' | 'ood'),
    and the real frames of evaluation episodes.
    tokenize -- the token store (T+1, h, w) of every episode, the tokenizer (to decode predicted
    frames for metrics and the figure) and its held-out IND episode list (reused here).

Outputs (in the artifact directory):
    action_wm.pt, text_wm.pt   checkpoints: architecture spec, weights, action clip range and
                               normalisation (buffers), decoding settings; read with
                               ``stages.train_wm.rollout.load_world_model(dir, kind)``
    proprio_head.pt            the action WM's proprioception head (``stages.train_wm.proprio``),
                               loaded with the action WM
    text_embeddings.json       {instruction: 384-d MiniLM embedding} of every instruction
    split.json                 train / held-out IND / OOD episode ids
    metrics.json               per model: loss history, wall time; action WM open-loop PSNR / SSIM /
                               LPIPS at horizons 1, 5, 15 on held-out IND and OOD next to the
                               copy-last-frame baseline and the tokenizer ceiling, controllability
                               (true vs shuffled actions), extreme-action rollouts; done-head AUROC,
                               precision / recall at ``done_threshold``, Brier, ECE for both models,
                               and their false alarms on near-miss and grasp-miss episodes
                               (collect's failures; the text WM trains on the other episodes only);
                               proprioception head: TCP error (cm) at horizons 1, 5, 15 vs copy-last
    frames.png                 real vs predicted frame strips (held-out IND and OOD)
    tensorboard/               training curves (both world models' losses, the proprioception head's)

Checkpoints (``ctx.checkpoints()``): ``action_wm`` and ``text_wm``, each model's training state,
    saved ``SAVES_PER_LOOP`` times during its training and after its last step
    (``stages.common.training_state``); a run killed mid-training resumes there and commits what an
    uninterrupted run commits (``seconds`` aside).

Key includes:
    this config (architecture, optimisation, decoding, evaluation sizes, seed) and the keys of the
    collect and tokenize artifacts. Device is not part of the key.

Toy profile:
    dim 32, 2 blocks, window 4, 120 steps of 4 clips per model: both models train for real and
    are evaluated in well under a minute on 2 cores; the numbers are not meaningful.
"""
from __future__ import annotations

import json
import time
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from stages.collect.plans import FAILURE_KINDS
from stages.common.frame_skip import frame_indices
from stages.train_wm.data import ClipSampler, load_episodes, split_episodes
from stages.train_wm.evaluate import (HORIZONS, decoded, done_head_eval, extreme_action_eval, false_alarm_rate,
                                      horizon_eval, real_images, rollout_starts)
from stages.train_wm.figure import frame_strips
from stages.train_wm.model import WMSpec, WorldModelNet
from stages.train_wm.rollout import CHECKPOINTS, TEXT_EMBEDDINGS, WorldModel, save_world_model
from stages.common.curves import Curves
from stages.common.training_state import save_every, training_checkpoint
from stages.train_wm.train import train_world_model


class Config(BaseModel):
    """train_wm stage configuration (defaults sized for the ``small`` profile)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, description="seed for initialisation, clip sampling, masking and evaluation choices")
    dim: int = Field(128, ge=8, description="transformer width")
    depth: int = Field(3, ge=1, description="spatial-temporal blocks in the backbone")
    heads: int = Field(4, ge=1, description="attention heads")
    head_depth: int = Field(1, ge=1, description="spatial blocks in the MaskGIT decoding head")
    mlp_ratio: int = Field(4, ge=1, description="MLP hidden width as a multiple of dim")
    frame_skip: int = Field(4, ge=1, description="control steps per world-model step: episodes are subsampled and "
                            "their actions composed (stages.common.frame_skip)")
    window: int = Field(8, ge=2, description="frames of temporal context (training clip length, KV cache size)")
    control_tokens: int = Field(4, ge=1, description="memory tokens the control (action / text) is projected into")
    action_steps: int = Field(3000, ge=1, description="optimisation steps of the action world model (at 800 it tied "
                              "copy-last and ignored its actions on the small data; 3000 beat it, docs/world_model.md)")
    text_steps: int = Field(800, ge=1, description="optimisation steps of the text world model (goal imagination, done head)")
    train_threads: int = Field(2, ge=1, description="torch CPU threads while training (rollouts and evaluation use "
                               "1); in the key: on a CPU the count changes the floating-point reductions, so the "
                               "weights (docs/rl.md, 'The thread count is part of the result')")
    batch_size: int = Field(8, ge=1, description="clips per optimisation step")
    lr: float = Field(1e-3, gt=0, description="AdamW peak learning rate")
    weight_decay: float = Field(0.05, ge=0, description="AdamW weight decay of matrices")
    done_loss: Literal["bce", "rmse"] = Field("bce", description="done-head loss: BCE (calibrated) or the paper's RMSE")
    done_weight: float = Field(1.0, ge=0, description="weight of the done loss next to the token cross-entropy")
    done_balance: bool = Field(True, description="done and not-done frames weigh half each in the done loss "
                               "(success frames are few: the last frames of successful episodes)")
    done_negatives: bool = Field(True, description="the action WM also trains on collect's failure episodes, "
                                 "near-misses and grasp-misses (never done); false = successful and suboptimal episodes only "
                                 "(the ablation)")
    changed_weight: float = Field(4.0, ge=1, description="cross-entropy weight of target tokens that changed since the "
                                  "previous frame (4 vs 1: h5 PSNR 24.79 vs 23.20 and 4x the gap to shuffled actions, "
                                  "docs/world_model.md)")
    context_noise: float = Field(0.0, ge=0, le=1, description="training: each clip's context frames get a random "
                                 "fraction in [0, context_noise] of their tokens replaced by random tokens (targets "
                                 "stay clean), meant to teach rollouts to recover from their own errors; 0 = off (0.2 changed nothing "
                                 "measurable, docs/world_model.md)")
    self_context: float = Field(0.0, ge=0, le=1, description="training: scheduled sampling, each context frame "
                                "after the first is with this probability the model's own one-step prediction "
                                "(greedy, one pass, no gradient; 1.3x the training time, measured); 0 = off (0.5 did not help, docs/world_model.md)")
    decode_steps: int = Field(2, ge=1, description="MaskGIT passes per predicted frame in rollouts")
    temperature: float = Field(0.0, ge=0, description="token sampling temperature in rollouts (0 = greedy)")
    holdout_fraction: float = Field(0.1, ge=0, lt=1, description="IND episodes held out if tokenize has no split.json")
    eval_episodes: int = Field(32, ge=1, description="episodes per split (held-out IND, OOD) used for evaluation")
    eval_starts: int = Field(4, ge=1, description="open-loop start frames per evaluation episode")
    done_threshold: float = Field(0.5, gt=0, lt=1, description="theta for done precision / recall")
    extreme_scale: float = Field(10.0, gt=1, description="extreme-action test: multiple of the data's action bound")
    proprio_steps: int = Field(3000, ge=1, description="optimisation steps of the proprioception head")
    proprio_batch_size: int = Field(256, ge=1, description="transitions per proprioception-head step")
    proprio_lr: float = Field(1e-3, gt=0, description="AdamW peak learning rate of the proprioception head")


def model_spec(cfg: Config, kind: str, vocab: int, grid: tuple[int, int]) -> WMSpec:
    """The architecture of the ``kind`` world model (action | text) this config trains."""
    return WMSpec(kind=kind, vocab_size=vocab, grid=grid, dim=cfg.dim, depth=cfg.depth, heads=cfg.heads,
                  head_depth=cfg.head_depth, mlp_ratio=cfg.mlp_ratio, window=cfg.window,
                  control_tokens=cfg.control_tokens, frame_skip=cfg.frame_skip)


def training_episodes(episodes: list, kind: str, done_negatives: bool) -> list:
    """The episodes the ``kind`` world model trains on.

    The text WM imagines goals from instructions: failures (near-misses, grasp-misses) would teach it
    that an instruction may end beside its goal, so it never sees them. The action WM trains on all of
    them (its done head learns from their never-done frames, its dynamics that a gripper closing
    beside the object leaves it where it is) unless ``done_negatives`` is off.
    """
    if kind == "action" and done_negatives:
        return list(episodes)
    return [e for e in episodes if e.kind not in FAILURE_KINDS]


def run(ctx) -> None:
    from stages.collect.dataset import Dataset
    from stages.common.text_encoder import encode_texts
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer

    cfg: Config = ctx.config
    cpu = ctx.device == "cpu"
    torch.manual_seed(cfg.seed)
    collect_dir, tok_dir = ctx.input("collect"), ctx.input("tokenize")
    store = TokenStore(tok_dir)
    n_eps = len(Dataset(collect_dir).episodes)
    with ctx.progress(n_eps, "train_wm: load episodes", unit="ep") as bar:
        episodes = load_episodes(collect_dir, tok_dir, bar, frame_skip=cfg.frame_skip)
    split_file = tok_dir / "split.json"
    heldout_ids = set(json.loads(split_file.read_text()).get("heldout", [])) if split_file.is_file() else None
    train_eps, held_eps, ood_eps = split_episodes(episodes, heldout_ids, cfg.holdout_fraction, cfg.seed)
    (ctx.out / "split.json").write_text(json.dumps({"train": [e.episode_id for e in train_eps],
                                                    "heldout": [e.episode_id for e in held_eps],
                                                    "ood": [e.episode_id for e in ood_eps]}, indent=1) + "\n")
    ctx.log.info("train_wm: %d IND train, %d held-out IND, %d OOD episodes", len(train_eps), len(held_eps), len(ood_eps))

    instructions = sorted({e.instruction for e in episodes})
    text_emb = dict(zip(instructions, encode_texts(instructions)))
    (ctx.out / TEXT_EMBEDDINGS).write_text(json.dumps({k: v.tolist() for k, v in text_emb.items()}) + "\n")

    vocab, grid = 2**store.bits, tuple(store.grid)
    train_actions = torch.from_numpy(np.concatenate([e.actions for e in train_eps]))
    metrics: dict = {"episodes/train": len(train_eps), "episodes/heldout_ind": len(held_eps),
                     "episodes/ood": len(ood_eps), "vocab_size": vocab, "grid": list(grid)}
    models = {}
    # training batches (8 clips x 8 frames x 64 tokens) use both cores: 0.53 s/step at 2 threads vs 0.85 at 1;
    # rollouts (a frame at a time) are faster at 1 thread (docs/world_model.md)
    if cpu:
        torch.set_num_threads(cfg.train_threads)
    curves = Curves(ctx.out)  # TensorBoard: both world models' losses and the proprioception head's
    checkpoints = ctx.checkpoints()  # a run killed while training resumes at the last saved step
    for i, kind in enumerate(("action", "text")):
        steps = cfg.action_steps if kind == "action" else cfg.text_steps
        net = WorldModelNet(model_spec(cfg, kind, vocab, grid)).to(ctx.device)
        net.set_action_stats(train_actions.to(ctx.device))
        clips = training_episodes(train_eps, kind, cfg.done_negatives)
        sampler = ClipSampler(clips, cfg.window, text_emb, cfg.seed + 17 * i)
        resume, save = training_checkpoint(checkpoints, f"{kind}_wm")
        with ctx.progress(steps, f"train_wm: {kind} WM", unit="step") as bar:
            result = train_world_model(net, sampler, steps=steps, batch_size=cfg.batch_size, lr=cfg.lr,
                                       weight_decay=cfg.weight_decay, done_weight=cfg.done_weight,
                                       done_kind=cfg.done_loss, seed=cfg.seed + i, device=ctx.device,
                                       changed_weight=cfg.changed_weight, done_balance=cfg.done_balance,
                                       context_noise=cfg.context_noise, self_context=cfg.self_context, progress=bar,
                                       log=ctx.log, desc=f"{kind}_wm", curves=curves, resume=resume, save=save,
                                       save_every=save_every(steps))
        save_world_model(net, ctx.out / CHECKPOINTS[kind],
                         {"decode_steps": cfg.decode_steps, "temperature": cfg.temperature})
        models[kind] = WorldModel(net, cfg.decode_steps, cfg.temperature, {k: v.tolist() for k, v in text_emb.items()})
        metrics[f"{kind}_wm/params"] = sum(p.numel() for p in net.parameters())
        metrics[f"{kind}_wm/train_seconds"] = result["seconds"]
        metrics[f"{kind}_wm/train_steps"] = steps
        metrics[f"{kind}_wm/final_ce"] = result["final"]["ce"]
        metrics[f"{kind}_wm/final_token_acc"] = result["final"]["acc"]
        metrics[f"{kind}_wm/final_done_loss"] = result["final"]["done"]
        metrics[f"{kind}_wm/history"] = result["history"]

    tok = load_tokenizer(tok_dir, ctx.device)
    metrics.update(_proprio_head(ctx, cfg, tok, train_eps, held_eps, ood_eps))
    curves.series("proprio/loss", metrics["proprio/history"])
    curves.close()

    if cpu:
        torch.set_num_threads(1)
    t0 = time.perf_counter()
    metrics.update(_evaluate(ctx, cfg, models, held_eps, ood_eps, text_emb, tok, Dataset(collect_dir)))
    metrics["eval_seconds"] = time.perf_counter() - t0
    ctx.write_metrics(metrics)


def _proprio_head(ctx, cfg: Config, tok, train_eps: list, held_eps: list, ood_eps: list) -> dict:
    """Train the action WM's proprioception head, save it, and measure its open-loop TCP error."""
    from stages.train_wm.proprio import CHECKPOINT, ProprioHead, horizon_errors, save_head, train_proprio_head, transitions

    def codes_fn(tokens: np.ndarray) -> torch.Tensor:  # (n, N) token ids -> (n, bits, h, w) +-1 codes
        return tok.codes(torch.from_numpy(tokens.reshape(len(tokens), *tok.grid)))

    head = ProprioHead(tok.bits, tok.grid).to(ctx.device)
    data = transitions(train_eps, codes_fn)
    with ctx.progress(cfg.proprio_steps, "train_wm: proprioception head", unit="step") as bar:
        result = train_proprio_head(head, data, steps=cfg.proprio_steps, batch_size=cfg.proprio_batch_size,
                                    lr=cfg.proprio_lr, seed=cfg.seed, device=ctx.device, progress=bar)
    save_head(head.cpu(), ctx.out / CHECKPOINT)
    head.to(ctx.device)
    out = {"proprio/train_seconds": result["seconds"], "proprio/final_loss": result["final"],
           "proprio/transitions": int(len(data[0])), "proprio/history": result["history"]}
    rng = np.random.default_rng(cfg.seed + 5)
    for split, eps in (("heldout_ind", held_eps), ("ood", ood_eps)):
        eps = [eps[i] for i in sorted(rng.choice(len(eps), size=min(cfg.eval_episodes, len(eps)), replace=False))] if eps else []
        starts = rollout_starts(eps, max(HORIZONS), cfg.eval_starts, rng)
        if starts:
            for k, v in horizon_errors(head, eps, codes_fn, HORIZONS, starts, ctx.device).items():
                out[f"proprio/{split}/{k}"] = v
    ctx.log.info("train_wm: proprioception head TCP error (cm) %s",
                 {k: round(v, 2) for k, v in out.items() if "tcp_error_cm" in k and "ci95" not in k and v is not None})
    return out


def _evaluate(ctx, cfg: Config, models: dict, held_eps: list, ood_eps: list, text_emb: dict, tok, ds) -> dict:
    """All evaluation metrics (see the module docstring) and ``frames.png``."""
    rng = np.random.default_rng(cfg.seed)
    metrics, panels = {}, []
    for split, eps in (("heldout_ind", held_eps), ("ood", ood_eps)):
        if not eps:
            ctx.log.warning("train_wm: no %s episodes, no metrics for that split", split)
            continue
        misses = {f: [e for e in eps if e.kind == f] for f in FAILURE_KINDS}
        eps = [eps[i] for i in sorted(rng.choice(len(eps), size=min(cfg.eval_episodes, len(eps)), replace=False))]
        for kind, wm in models.items():
            for k, v in done_head_eval(wm, eps, cfg.done_threshold, text_emb).items():
                metrics[f"{kind}_wm/{split}/done/{k}"] = v
            for failure, fail_eps in misses.items():
                for k, v in false_alarm_rate(wm, fail_eps, cfg.done_threshold, text_emb).items():
                    metrics[f"{kind}_wm/{split}/done/{failure}/{k}"] = v
        starts = rollout_starts(eps, max(HORIZONS), cfg.eval_starts, rng)
        if not starts:
            ctx.log.warning("train_wm: %s episodes are shorter than %d steps, no horizon metrics", split, max(HORIZONS))
            continue
        used = sorted({i for i, _ in starts})
        images = {}
        with ctx.progress(len(used), f"train_wm: {split} frames", unit="ep") as bar:
            for i in used:
                ep = ds.load(eps[i].episode_id)
                keep = frame_indices(len(ep.action), cfg.frame_skip)  # the world model's frames
                images[eps[i].episode_id] = real_images(tok, ep.third[keep], ep.wrist[keep])
                bar.update(1)
        rows = {}
        for kind, wm in models.items():
            m, strip = horizon_eval(wm, tok, eps, images, starts, text_emb, ctx.device,
                                    controllability=(kind == "action"))
            metrics.update({f"{kind}_wm/{split}/{k}": v for k, v in m.items()})
            i, s = strip["start"]
            if not rows:
                rows["real"] = images[eps[i].episode_id][s : s + max(HORIZONS) + 1]
            start = decoded(tok, torch.from_numpy(eps[i].tokens[s]).view(1, *wm.spec.grid))
            rows[f"{kind} WM"] = torch.cat([start, decoded(tok, strip["pred"])])
        panels.append((f"{split} {eps[i].episode_id.split('.')[0]}", rows))
        for k, v in extreme_action_eval(models["action"], tok, eps, starts, max(HORIZONS), cfg.extreme_scale,
                                        cfg.seed).items():
            metrics[f"action_wm/{split}/extreme_actions/{k}"] = v
    if panels:
        frame_strips(panels, ctx.out / "frames.png")
    return metrics
