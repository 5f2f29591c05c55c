"""Training and evaluation of the tokenizer on in-memory uint8 frames of both views."""
from __future__ import annotations

import copy
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from stages.common import image_metrics
from stages.common.lpips import get_lpips
from stages.tokenize.model import TokenizerNet, from_obs, to_obs


@dataclass(frozen=True)
class TrainSettings:
    """The optimisation part of the stage config (see ``stages.tokenize.Config`` for meanings)."""

    steps: int
    batch_size: int
    lr: float
    warmup_steps: int
    weight_decay: float
    recon_loss: str
    lpips_weight: float
    lpips_batch: int
    entropy_weight: float
    commitment_weight: float
    grad_clip: float


@dataclass
class TrainLog:
    """Loss history of one training run (averaged over windows of ``every`` steps)."""

    every: int
    recon: list[float] = field(default_factory=list)
    lpips: list[float] = field(default_factory=list)
    entropy: list[float] = field(default_factory=list)
    seconds: float = 0.0


def lr_at(step: int, s: TrainSettings) -> float:
    """Linear warm-up then cosine decay to 10% of ``lr``."""
    if step < s.warmup_steps:
        return s.lr * (step + 1) / s.warmup_steps
    frac = (step - s.warmup_steps) / max(1, s.steps - s.warmup_steps)
    return s.lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * frac)))


def _lpips_loss(recon: torch.Tensor, target: torch.Tensor, n: int, device: str) -> torch.Tensor:
    """Mean LPIPS over both views of the first ``n`` samples; recon/target (B, 6, S, S) in [-1, 1]."""
    net = get_lpips(device)
    r, t = recon[:n], target[:n]
    r = torch.cat([r[:, :3], r[:, 3:]])  # (2n, 3, S, S): views side by side in the batch
    t = torch.cat([t[:, :3], t[:, 3:]])
    return net(r, t).mean()


def train(
    net: TokenizerNet,
    third: np.ndarray,
    wrist: np.ndarray,
    s: TrainSettings,
    *,
    seed: int,
    device: str = "cpu",
    progress=None,
    log=None,
    curves=None,
    resume: dict | None = None,
    save: Callable[[dict], None] | None = None,
    save_every: int = 0,
) -> TrainLog:
    """Train ``net`` in place on uint8 frames third/wrist (N, H, W, 3); returns the loss history.

    ``curves`` (``stages.common.curves.Curves``), when given, receives every history point as
    ``tokenizer/<loss>`` (and the learning rate) so the run can be watched in TensorBoard.

    Resuming: with ``save``, every ``save_every`` steps and after the last one the loop hands ``save``
    its whole state (weights, optimiser, the batch generator's and torch's RNG, the history, the
    running sums, the curve points, seconds so far); a later call given that dict as ``resume``, on the
    same frames and settings, continues from it and ends with the weights and history an uninterrupted
    run has (tests/tokenize/test_resume.py). ``seconds`` counts the training time of every part.
    """
    if len(third) == 0:
        raise ValueError("tokenizer training got no frames: no IND training episodes in the collect artifact?")
    net.to(device).train()
    opt = torch.optim.AdamW(net.parameters(), lr=s.lr, weight_decay=s.weight_decay, betas=(0.9, 0.99))
    gen = np.random.default_rng(seed)
    third_t, wrist_t = torch.from_numpy(third), torch.from_numpy(wrist)  # (N, H, W, 3) uint8, CPU
    hist = TrainLog(every=max(1, s.steps // 50))
    acc = {"recon": 0.0, "lpips": 0.0, "entropy": 0.0}
    points: list[tuple[str, float, int]] = []  # (tag, value, step): the curves, rewritten after a resume
    start, before = 0, 0.0
    if resume is not None:
        start, before, hist, acc, points = _restore(resume, net, opt, gen, len(third), s)
        for tag, v, at in points if curves is not None else ():  # the killed run's curves left with its staging dir
            curves.scalar(tag, v, at)
        if progress is not None:
            progress.resumed(start)
        if log is not None:
            log.info("tokenize resumed at step %d/%d from a checkpoint", start, s.steps)
    t0 = time.perf_counter()
    for step in range(start, s.steps):
        idx = torch.from_numpy(gen.integers(0, len(third), size=s.batch_size))
        obs = to_obs(third_t[idx].to(device), wrist_t[idx].to(device), net.spec.image_size)  # (B, 6, S, S)
        recon, q = net(obs)
        rec = F.l1_loss(recon, obs) if s.recon_loss == "l1" else F.mse_loss(recon, obs)
        loss = rec + s.entropy_weight * q.entropy_loss + s.commitment_weight * q.commitment_loss
        lp = torch.zeros((), device=device)
        if s.lpips_weight > 0 and s.lpips_batch > 0:
            lp = _lpips_loss(recon, obs, s.lpips_batch, device)
            loss = loss + s.lpips_weight * lp
        if not torch.isfinite(loss):
            raise FloatingPointError(f"tokenizer loss became {loss.item()} at step {step}; lower tokenize.lr (now {s.lr})")
        for g in opt.param_groups:
            g["lr"] = lr_at(step, s)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if s.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(net.parameters(), s.grad_clip)
        opt.step()
        acc["recon"] += rec.item()
        acc["lpips"] += lp.item()
        acc["entropy"] += q.entropy_loss.item()
        if (step + 1) % hist.every == 0 or step + 1 == s.steps:
            n = (step % hist.every) + 1
            new = []
            for k in acc:
                getattr(hist, k).append(acc[k] / n)
                acc[k] = 0.0
                new.append((f"tokenizer/{k}", getattr(hist, k)[-1], step + 1))
            new.append(("tokenizer/lr", lr_at(step, s), step + 1))
            points += new
            for tag, v, at in new if curves is not None else ():
                curves.scalar(tag, v, at)
            if log is not None and len(hist.recon) % 10 == 0:
                log.info("tokenize step %d/%d recon %.4f lpips %.4f entropy %.3f", step + 1, s.steps, hist.recon[-1], hist.lpips[-1], hist.entropy[-1])
        if progress is not None:
            progress.update(1)
            progress.postfix(recon=f"{rec.item():.4f}", lpips=f"{lp.item():.3f}")
        if save is not None and (step + 1 == s.steps or (save_every > 0 and (step + 1) % save_every == 0)):
            hist.seconds = before + time.perf_counter() - t0
            save(_state(step + 1, hist, acc, points, net, opt, gen, len(third), s))
    hist.seconds = before + time.perf_counter() - t0
    net.eval()
    return hist


def _state(step: int, hist: TrainLog, acc: dict, points: list, net: TokenizerNet, opt, gen: np.random.Generator,
           frames: int, s: TrainSettings) -> dict:
    """Everything the loop's remaining steps depend on after ``step`` steps, as copies the later steps
    leave alone; ``frames`` and the settings are kept to refuse a resume on other data."""
    return {"step": step, "hist": asdict(hist), "acc": dict(acc), "points": list(points),
            "net": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
            "opt": copy.deepcopy(opt.state_dict()), "gen": copy.deepcopy(gen.bit_generator.state),
            "torch_rng": torch.get_rng_state(), "frames": frames, "settings": asdict(s)}


def _restore(state: dict, net: TokenizerNet, opt, gen: np.random.Generator, frames: int, s: TrainSettings) -> tuple:
    """Load ``state`` (from ``_state``) into the loop's objects; (step, seconds, hist, acc, points)."""
    if state["frames"] != frames or state["settings"] != asdict(s):
        raise ValueError(f"tokenize checkpoint from training on {state['frames']} frames with {state['settings']}, "
                         f"this run trains on {frames} frames with {asdict(s)}: not the same run; "
                         "remove the store's partial/tokenize/<key> directory or run with --force")
    net.load_state_dict(state["net"])
    opt.load_state_dict(state["opt"])
    gen.bit_generator.state = state["gen"]
    torch.set_rng_state(state["torch_rng"])
    hist = TrainLog(**state["hist"])
    return state["step"], hist.seconds, hist, dict(state["acc"]), list(state["points"])


@torch.no_grad()
def reconstruct(net: TokenizerNet, third: np.ndarray, wrist: np.ndarray, device: str = "cpu", batch_size: int = 128):
    """(third, wrist, tokens): reconstructions (N, 3, S, S) in [0, 1] on CPU and tokens (N, h, w) int64."""
    net.eval()
    outs_t, outs_w, toks = [], [], []
    for i in range(0, len(third), batch_size):
        obs = to_obs(torch.from_numpy(third[i : i + batch_size]).to(device), torch.from_numpy(wrist[i : i + batch_size]).to(device), net.spec.image_size)
        q, tok = net.quantizer.quantize(net.latents(obs))
        rt, rw = from_obs(net.decode_codes(q))
        outs_t.append(rt.cpu()), outs_w.append(rw.cpu()), toks.append(tok.cpu())
    return torch.cat(outs_t), torch.cat(outs_w), torch.cat(toks)


def target_images(views: np.ndarray, size: int) -> torch.Tensor:
    """uint8 (N, H, W, 3) -> (N, 3, size, size) in [0, 1], resized the way the tokenizer sees it."""
    x = torch.from_numpy(views).permute(0, 3, 1, 2).float()
    if x.shape[-1] != size:
        x = F.interpolate(x, size=(size, size), mode="area" if x.shape[-1] > size else "bilinear")
    return x / 255.0


def evaluate(net: TokenizerNet, third: np.ndarray, wrist: np.ndarray, device: str = "cpu") -> dict[str, float]:
    """PSNR / SSIM / LPIPS per view and codebook usage of these frames' tokens."""
    if len(third) == 0:
        return {}
    rt, rw, tok = reconstruct(net, third, wrist, device)
    out = {}
    for name, real, rec in (("third", third, rt), ("wrist", wrist, rw)):
        for k, v in image_metrics.summary(target_images(real, net.spec.image_size), rec, device).items():
            out[f"{name}_{k}"] = v
    out.update(codebook_usage(tok.numpy(), net.spec.bits))
    out["frames"] = int(len(third))
    return out


def codebook_usage(tokens: np.ndarray, bits: int) -> dict[str, float]:
    """Fraction of the 2^bits codes that occur in ``tokens`` and the perplexity of their histogram."""
    return usage_from_counts(np.bincount(np.asarray(tokens, dtype=np.int64).ravel(), minlength=2**bits))


def usage_from_counts(counts: np.ndarray) -> dict[str, float]:
    """Code usage statistics from a histogram (2^bits,) of token ids."""
    p = counts[counts > 0] / max(1, counts.sum())
    return {"code_usage": float((counts > 0).mean()), "code_perplexity": float(np.exp(-(p * np.log(p)).sum())), "codes_used": int((counts > 0).sum())}
