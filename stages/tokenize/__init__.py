"""tokenize: train a MAGVIT-2-style LFQ tokenizer on collected frames and tokenize every episode.

Inputs:
    collect -- the collect artifact, read through ``stages.collect.dataset.Dataset``: every
    episode's third-view and wrist-view uint8 frames, with its split ('ind' | 'ood').

Outputs (in the artifact directory):
    tokenizer.pt   the checkpoint (architecture spec + weights); ``load_tokenizer(dir)`` reads it
    tokens.npy     uint16 (N_frames, h, w): every frame of every episode (IND and OOD), memory-mappable
    index.json     {grid, bits, episodes: {episode_id: [offset, length]}}; ``TokenStore(dir)`` reads it
    split.json     the IND episodes trained on and the held-out IND episodes used for metrics
    metrics.json   PSNR / SSIM / LPIPS per view on held-out IND and on OOD frames, codebook usage
                   (fraction of codes used, perplexity), loss history, training time
    recon.png      real vs reconstructed strips (held-out IND and OOD, both views)
    tensorboard/   the training curves (losses, learning rate) as TensorBoard event files

Checkpoints (``ctx.checkpoints()``): ``tokenizer``, the training state, saved ``SAVES_PER_LOOP``
    times during training and after its last step (``stages.common.training_state``); a run killed
    mid-training resumes there and commits what an uninterrupted run commits (``seconds`` aside).
    ``encode-<i>``, the tokens of the i-th run of ``ENCODE_CHUNK`` episodes, saved as the encoding
    goes: a run killed while encoding keeps the chunks it finished and encodes only the rest.

Key includes:
    this config (architecture, loss weights, steps, seed) and the collect artifact's key. Device and
    worker count are not part of the key.

Toy profile:
    a tiny network (channels 8/16/32, 8 bits) for 50 steps on at most 2000 frames: ~25 s for the
    whole stage on 2 cores. It trains for real but only reconstructs blurry mean images.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from pipeline.context import StageContext
from stages.common.curves import Curves
from stages.common.training_state import save_every, training_checkpoint
from stages.tokenize import train as training
from stages.tokenize.model import ModelSpec, TokenizerNet
from stages.tokenize.store import TOKENS, TokenStore, write_index
from stages.tokenize.tokenizer import Tokenizer, load_tokenizer, save_checkpoint

# episodes per encoding checkpoint: ~1 min of encoding at `small` on 2 CPU cores (896 episodes, ~10 min)
ENCODE_CHUNK = 64

__all__ = ["Config", "run", "load_tokenizer", "Tokenizer", "TokenStore"]


class Config(BaseModel):
    """The tokenize stage's config section (defaults: the ``small`` profile)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, description="seed for initialisation, episode hold-out and batch sampling")
    image_size: int = Field(64, description="square resolution each view is resized to before encoding (pixels)")
    bits: int = Field(10, ge=1, le=16, description="LFQ bits per token; codebook size is 2^bits")
    channels: tuple[int, ...] = Field((32, 64, 128), description="encoder width after each 2x downsampling; len = number of halvings")
    res_blocks: int = Field(1, ge=0, description="residual blocks per resolution level in encoder and decoder")
    temperature: float = Field(1.0, gt=0, description="LFQ softmax temperature for the entropy loss")
    per_view: bool = Field(True, description="one token grid per view (stacked vertically, 2x the tokens) "
                           "instead of one grid for both views stacked as channels (docs/tokenizer.md)")
    steps: int = Field(1500, ge=1, description="optimiser steps")
    batch_size: int = Field(32, ge=1, description="observations (frame pairs) per step")
    lr: float = Field(5e-4, gt=0, description="peak AdamW learning rate")
    warmup_steps: int = Field(50, ge=0, description="linear learning-rate warm-up steps, then cosine decay to 10%")
    weight_decay: float = Field(0.0, ge=0, description="AdamW weight decay")
    recon_loss: Literal["l1", "l2"] = Field("l1", description="pixel reconstruction loss")
    lpips_weight: float = Field(1.0, ge=0, description="weight of the LPIPS perceptual loss (0 disables it)")
    lpips_batch: int = Field(8, ge=0, description="how many samples of each batch get the (costly) LPIPS loss")
    entropy_weight: float = Field(0.1, ge=0, description="weight of the LFQ entropy loss")
    commitment_weight: float = Field(0.25, ge=0, description="weight of the LFQ commitment loss")
    grad_clip: float = Field(1.0, ge=0, description="gradient-norm clip (0 disables it)")
    max_train_frames: int = Field(20000, ge=1, description="cap on training frames held in memory (random subset)")
    holdout_fraction: float = Field(0.1, ge=0, lt=1, description="fraction of IND episodes held out of training, for metrics")
    eval_frames: int = Field(256, ge=1, description="frames per split (held-out IND, OOD) used for metrics")
    figure_frames: int = Field(8, ge=1, description="frames per strip in recon.png")
    encode_batch: int = Field(256, ge=1, description="frames per batch when tokenizing every episode")

    def spec(self) -> ModelSpec:
        return ModelSpec(image_size=self.image_size, bits=self.bits, channels=tuple(self.channels), res_blocks=self.res_blocks, temperature=self.temperature,
                         per_view=self.per_view)

    def settings(self) -> training.TrainSettings:
        return training.TrainSettings(
            steps=self.steps, batch_size=self.batch_size, lr=self.lr, warmup_steps=self.warmup_steps, weight_decay=self.weight_decay,
            recon_loss=self.recon_loss, lpips_weight=self.lpips_weight, lpips_batch=self.lpips_batch,
            entropy_weight=self.entropy_weight, commitment_weight=self.commitment_weight, grad_clip=self.grad_clip,
        )


def open_dataset(path):
    """The collect artifact's ``Dataset`` (imported here so the tokenizer API does not need the simulator)."""
    from stages.collect.dataset import Dataset

    return Dataset(path)


def heldout_split(ind: list, fraction: float, rng: np.random.Generator) -> tuple[list, list]:
    """(train, held-out) IND episodes: a random ``fraction`` held out (at least one when there are two)."""
    order = rng.permutation(len(ind))
    n_hold = 0 if len(ind) < 2 or fraction == 0 else max(1, round(fraction * len(ind)))
    return [ind[i] for i in sorted(order[n_hold:])], [ind[i] for i in order[:n_hold]]


def write_split(out: Path, train_eps: list, held: list) -> None:
    """``split.json``: the episode ids the tokenizer trained on and those held out of every stage's training."""
    (out / "split.json").write_text(json.dumps({"train": [e.episode_id for e in train_eps],
                                                "heldout": [e.episode_id for e in held]}, indent=1) + "\n")


def _load_frames(ds, episodes, max_frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Both views of a random subset of at most ``max_frames`` frames of ``episodes`` (EpisodeMeta), (N, H, W, 3) uint8.

    Every episode contributes the same fraction of its frames, chosen while loading, so memory stays
    bounded by ``max_frames`` whatever the dataset size.
    """
    total = sum(e.length + 1 for e in episodes)
    frac = min(1.0, max_frames / max(1, total))
    thirds, wrists = [], []
    for e in episodes:
        ep = ds.load(e.episode_id)
        keep = np.sort(rng.choice(len(ep.third), size=max(1, int(round(frac * len(ep.third)))), replace=False))
        thirds.append(ep.third[keep]), wrists.append(ep.wrist[keep])
    if not thirds:
        return np.zeros((0, 1, 1, 3), np.uint8), np.zeros((0, 1, 1, 3), np.uint8)
    third, wrist = np.concatenate(thirds), np.concatenate(wrists)
    if len(third) > max_frames:  # rounding overshoot
        keep = np.sort(rng.choice(len(third), size=max_frames, replace=False))
        third, wrist = third[keep], wrist[keep]
    return third, wrist


def _episodes_for_frames(rng: np.random.Generator, episodes, n_frames: int) -> list:
    """A random subset of ``episodes`` (EpisodeMeta) holding at least ``n_frames`` frames, or all of them."""
    out, total = [], 0
    for i in rng.permutation(len(episodes)):
        if total >= n_frames:
            break
        out.append(episodes[i])
        total += episodes[i].length + 1
    return out


def run(ctx: StageContext) -> None:
    cfg: Config = ctx.config
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    ds = open_dataset(ctx.input("collect"))
    ind = [e for e in ds.episodes if e.split == "ind"]
    ood = [e for e in ds.episodes if e.split == "ood"]
    if not ind:
        raise ValueError(f"collect artifact {ctx.input('collect')} has no IND episodes to train the tokenizer on")
    train_eps, held = heldout_split(ind, cfg.holdout_fraction, rng)
    write_split(ctx.out, train_eps, held)
    ctx.log.info("tokenize: %d IND train episodes, %d held out, %d OOD", len(train_eps), len(held), len(ood))

    third, wrist = _load_frames(ds, train_eps, cfg.max_train_frames, rng)
    ctx.log.info("tokenize: training on %d frames of %s", len(third), third.shape[1:])
    net = TokenizerNet(cfg.spec())
    resume, save = training_checkpoint(ctx.checkpoints(), "tokenizer")  # a killed run resumes at its last save
    with ctx.progress(cfg.steps, "tokenize train", unit="step") as bar, Curves(ctx.out) as curves:
        hist = training.train(net, third, wrist, cfg.settings(), seed=cfg.seed, device=ctx.device, progress=bar,
                              log=ctx.log, curves=curves, resume=resume, save=save, save_every=save_every(cfg.steps))
    del third, wrist
    save_checkpoint(net.cpu(), ctx.out)
    net.to(ctx.device)

    metrics: dict = {"train_seconds": hist.seconds, "train_steps": cfg.steps, "steps_per_second": cfg.steps / max(hist.seconds, 1e-9)}
    metrics["loss_recon_first"], metrics["loss_recon_last"] = hist.recon[0], hist.recon[-1]
    metrics["loss_lpips_first"], metrics["loss_lpips_last"] = hist.lpips[0], hist.lpips[-1]
    metrics["loss_history"] = {"every": hist.every, "recon": hist.recon, "lpips": hist.lpips, "entropy": hist.entropy}
    panels = []
    for split, eps in (("heldout_ind", held), ("ood", ood)):
        t, w = _load_frames(ds, _episodes_for_frames(rng, eps, cfg.eval_frames), cfg.eval_frames, rng)
        if len(t) == 0:
            ctx.log.warning("tokenize: no %s frames, no metrics for that split", split)
            continue
        for k, v in training.evaluate(net, t, w, ctx.device).items():
            metrics[f"{split}/{k}"] = v
        pick = np.linspace(0, len(t) - 1, min(cfg.figure_frames, len(t))).round().astype(int)
        rt, rw, _ = training.reconstruct(net, t[pick], w[pick], ctx.device)
        panels.append((split, {"third real": training.target_images(t[pick], cfg.image_size), "third recon": rt,
                               "wrist real": training.target_images(w[pick], cfg.image_size), "wrist recon": rw}))
    from stages.tokenize.figure import save_recon_figure  # matplotlib only where the figure is drawn

    save_recon_figure(ctx.out / "recon.png", panels)

    tokenizer = Tokenizer(net, ctx.device)
    with ctx.progress(len(ds.episodes), "tokenize encode", unit="ep") as bar:
        found = encode_all(ctx.out, ds, tokenizer, cfg.encode_batch, bar, checkpoints=ctx.checkpoints(), log=ctx.log)
        metrics.update({f"all/{k}": v for k, v in found.items()})
    metrics.update({"bits": cfg.bits, "vocab_size": 2**cfg.bits, "grid": list(tokenizer.grid), "tokens_per_frame": tokenizer.grid[0] * tokenizer.grid[1]})
    ctx.write_metrics(metrics)
    ctx.log.info("tokenize: done in %.0f s of training; metrics %s", hist.seconds,
                 {k: round(v, 4) for k, v in metrics.items() if isinstance(v, float) and "/" in k})


def encode_all(out: Path, ds, tok: Tokenizer, batch: int, bar=None, checkpoints=None, log=None) -> dict:
    """Tokenize every frame of every episode of ``ds`` into ``out/tokens.npy`` + ``out/index.json``; codebook
    usage over all. ``bar``: a progress bar (``update(n)``) or None. ``checkpoints`` (``ctx.checkpoints()``
    or None): each run of ``ENCODE_CHUNK`` episodes is saved there once encoded, and a chunk an earlier run
    of this key saved is read back instead of encoded again (the same weights give the same tokens)."""
    episodes = ds.episodes
    offsets, n = {}, 0
    for e in episodes:
        offsets[e.episode_id] = (n, e.length + 1)
        n += e.length + 1
    tokens = np.lib.format.open_memmap(out / TOKENS, mode="w+", dtype=np.uint16, shape=(n, *tok.grid))  # (N_frames, h, w)
    reused = 0
    for i, start in enumerate(range(0, len(episodes), ENCODE_CHUNK)):
        chunk = episodes[start : start + ENCODE_CHUNK]
        lo = offsets[chunk[0].episode_id][0]
        hi = sum(offsets[chunk[-1].episode_id])
        name = f"encode-{i}"
        found = checkpoints.load(name) if checkpoints is not None else None
        if found is not None:
            ids = np.load(found / TOKENS)  # (frames of the chunk, h, w) uint16
            if ids.shape != (hi - lo, *tok.grid):
                raise ValueError(f"tokenize checkpoint {found} holds tokens {ids.shape}, but episodes {start}.."
                                 f"{start + len(chunk) - 1} have {hi - lo} frames of grid {tok.grid}: not this run's")
            tokens[lo:hi] = ids
            reused += len(chunk)
        else:
            for e in chunk:
                ep = ds.load(e.episode_id)
                off, length = offsets[e.episode_id]
                if len(ep.third) != length:
                    raise ValueError(f"episode {e.episode_id}: index says length {e.length} (so {length} frames) but it has {len(ep.third)} frames")
                tokens[off : off + length] = tok.encode(ep.third, ep.wrist, batch_size=batch).cpu().numpy().astype(np.uint16)  # (T+1, h, w)
            if checkpoints is not None:
                with checkpoints.save(name) as d:
                    np.save(d / TOKENS, np.asarray(tokens[lo:hi]))
        if bar is not None:
            bar.update(len(chunk))
    if reused and log is not None:
        log.info("tokenize: %d of %d episodes' tokens read back from an earlier run's checkpoints", reused, len(episodes))
    counts = np.zeros(tok.vocab_size, dtype=np.int64)
    for start in range(0, n, 65536):  # codebook usage over every frame, from the written array
        counts += np.bincount(np.asarray(tokens[start : start + 65536]).ravel(), minlength=tok.vocab_size)
    tokens.flush()
    del tokens
    write_index(out, tok.grid, tok.bits, offsets)
    return {"frames": int(n), "episodes": len(episodes), **training.usage_from_counts(counts)}
