"""Training loop of one world model: masked-token cross-entropy on next frames plus the done loss."""
from __future__ import annotations

import copy
import math
import time
from typing import Callable

import torch
import torch.nn.functional as F

from stages.train_wm.data import ClipSampler, corrupt_context, mix_context, random_mask
from stages.train_wm.model import WorldModelNet


def done_loss(logit: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, kind: str,
              balance: bool = False) -> torch.Tensor:
    """Done loss over valid frames. logit/target/valid (B, T). ``bce`` or the paper's ``rmse`` on probabilities.

    ``balance``: done and not-done frames weigh half each (whichever are present in the batch), so
    the few success frames at episode ends count as much as the many frames before them.
    """
    if kind == "bce":
        per = F.binary_cross_entropy_with_logits(logit, target, reduction="none")  # (B, T)
    elif kind == "rmse":
        per = (torch.sigmoid(logit) - target) ** 2  # (B, T)
    else:
        raise ValueError(f"done loss must be 'bce' or 'rmse', got {kind!r}")
    if balance:
        pos, neg = valid * (target > 0.5), valid * (target <= 0.5)  # (B, T)
        parts = [(per * m).sum() / m.sum() for m in (pos, neg) if m.sum() > 0]
        loss = sum(parts) / max(len(parts), 1) if parts else (per * valid).sum()
    else:
        loss = (per * valid).sum() / valid.sum().clamp_min(1.0)
    return torch.sqrt(loss + 1e-8) if kind == "rmse" else loss


# Eq. 5: token cross-entropy plus the done loss (weighted by done_weight in train_world_model)
def losses(net: WorldModelNet, batch: dict, gen: torch.Generator, done_kind: str,
           changed_weight: float = 1.0, done_balance: bool = False, context_noise: float = 0.0,
           self_context: float = 0.0) -> dict[str, torch.Tensor]:
    """Token cross-entropy over hidden target tokens, token accuracy, and the done loss of one batch.

    ``changed_weight`` multiplies the cross-entropy of target tokens that differ from the previous
    frame's token at that position (the few tokens that carry the action's effect). ``context_noise``:
    the backbone reads context frames with up to this fraction of random tokens (targets stay clean).
    ``self_context``: that fraction of context frames is the model's own one-step prediction
    (scheduled sampling, ``data.mix_context``; one extra forward pass without gradients).
    """
    tokens, valid = batch["tokens"], batch["valid"]  # (B, T+1, N), (B, T)
    b, t1, n = tokens.shape
    mask = random_mask((b, t1 - 1, n), gen, tokens.device)  # (B, T, N)
    control = batch["actions"] if net.spec.kind == "action" else batch["text"]
    context = corrupt_context(tokens[:, :-1], context_noise, net.spec.vocab_size, gen)  # (B, T, N)
    if self_context > 0:
        context = mix_context(context, own_predictions(net, tokens, control, context), self_context, gen)
    logits, done = net(tokens, control, mask, context)  # (B, T, N, V), (B, T)
    target = tokens[:, 1:]
    changed = (target != tokens[:, :-1]).float()  # (B, T, N)
    hidden = mask.float() * valid[..., None]  # (B, T, N)
    weight = hidden * (1.0 + (changed_weight - 1.0) * changed)
    ce = F.cross_entropy(logits.flatten(0, 2), target.flatten(), reduction="none").view(b, t1 - 1, n)
    ce = (ce * weight).sum() / weight.sum().clamp_min(1.0)
    acc = ((logits.argmax(-1) == target).float() * hidden).sum() / hidden.sum().clamp_min(1.0)
    dl = done_loss(done, batch["done"], valid, done_kind, done_balance)
    return {"ce": ce, "done": dl, "acc": acc}


@torch.no_grad()
def own_predictions(net: WorldModelNet, tokens: torch.Tensor, control: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
    """The model's greedy one-pass predictions (B, T, N) of frames 1..T from ``context`` (B, T, N), all targets hidden."""
    b, t1, n = tokens.shape
    logits, _ = net(tokens, control, torch.ones(b, t1 - 1, n, dtype=torch.bool, device=tokens.device), context)
    return logits.argmax(-1)  # (B, T, N)


def train_world_model(net: WorldModelNet, sampler: ClipSampler, *, steps: int, batch_size: int, lr: float,
                      weight_decay: float, done_weight: float, done_kind: str, seed: int, device,
                      changed_weight: float = 1.0, done_balance: bool = False, context_noise: float = 0.0,
                      self_context: float = 0.0, progress=None, log=None, desc: str = "", curves=None,
                      resume: dict | None = None, save: Callable[[dict], None] | None = None,
                      save_every: int = 0) -> dict:
    """Train ``net`` in place with AdamW (linear warm-up, cosine decay); returns the loss history and time.

    ``curves`` (``stages.common.curves.Curves``), when given, receives the same points as the history
    under ``<desc>/<loss>`` so the run can be watched in TensorBoard.

    Resuming: with ``save``, every ``save_every`` steps and after the last one the loop hands
    ``save`` its whole state (weights, optimiser, schedule, the mask generator, the clip sampler's
    and torch's global RNG, history, curve points, seconds so far); a later call given that dict as
    ``resume`` continues from it and ends with the weights, history and RNG states a run without
    the interruption has (tests/train_wm/test_resume.py). ``seconds`` counts the training time of
    every part.
    """
    net.train()
    gen = torch.Generator().manual_seed(seed)
    decay = [p for p in net.parameters() if p.dim() >= 2]
    no_decay = [p for p in net.parameters() if p.dim() < 2]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": weight_decay},
                             {"params": no_decay, "weight_decay": 0.0}], lr=lr, betas=(0.9, 0.95))
    warmup = max(1, steps // 20)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / warmup) * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(s / steps, 1.0)))))
    history, points, ema, start, before = [], [], None, 0, 0.0
    if resume is not None:
        start, before, history, points, ema = _restore(resume, net, opt, sched, gen, sampler)
        if curves is not None:  # the curves the interrupted run wrote went with its staging directory
            for tag, v, s in points:
                curves.scalar(tag, v, s)
        if progress is not None:
            progress.resumed(start)  # counted, but not in the rate: the ETA is this run's
        if log is not None:
            log.info("%s resumed at step %d/%d from a checkpoint", desc, start, steps)
    t0 = time.perf_counter()
    # bf16 autocast only on CUDA: on a 2-core CPU without native bf16, bf16 matmuls ran at ~1 GFLOP/s (fp32 ~85)
    use_bf16 = torch.device(device).type == "cuda"
    for step in range(start, steps):
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=use_bf16):
            out = losses(net, sampler.sample(batch_size, device), gen, done_kind, changed_weight, done_balance,
                         context_noise, self_context)
        loss = out["ce"] + done_weight * out["done"]
        if not torch.isfinite(loss):
            raise FloatingPointError(f"{desc} world-model loss became {loss.item()} at step {step}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
        vals = {k: float(v.detach()) for k, v in out.items()}
        ema = vals if ema is None else {k: 0.9 * ema[k] + 0.1 * vals[k] for k in vals}
        if step % max(1, steps // 50) == 0 or step == steps - 1:
            history.append({"step": step, **vals})
            new = [(f"{desc}/{k}", v, step) for k, v in vals.items()] + [(f"{desc}/lr", sched.get_last_lr()[0], step)]
            points += new
            if curves is not None:
                for tag, v, s in new:
                    curves.scalar(tag, v, s)
        if progress is not None:
            progress.update(1)
            progress.postfix(ce=f"{ema['ce']:.3f}", acc=f"{ema['acc']:.2f}", done=f"{ema['done']:.3f}")
        if log is not None and (step % max(1, steps // 10) == 0 or step == steps - 1):
            log.info("%s step %d/%d ce %.4f acc %.3f done %.4f", desc, step, steps, ema["ce"], ema["acc"], ema["done"])
        if save is not None and (step == steps - 1 or (save_every > 0 and (step + 1) % save_every == 0)):
            save(_state(step + 1, before + time.perf_counter() - t0, history, points, ema, net, opt, sched, gen, sampler))
    net.eval()
    return {"history": history, "seconds": before + time.perf_counter() - t0, "final": ema}


def _state(step: int, seconds: float, history: list, points: list, ema: dict | None, net, opt, sched,
           gen: torch.Generator, sampler: ClipSampler) -> dict:
    """Everything the loop's remaining steps depend on, after ``step`` steps: copies, which later steps
    leave alone (the optimiser's state dict holds its live moment tensors)."""
    return {"step": step, "seconds": seconds, "history": list(history), "points": list(points), "ema": ema,
            "net": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
            "opt": copy.deepcopy(opt.state_dict()), "sched": sched.state_dict(), "gen": gen.get_state(),
            "sampler": sampler.rng.bit_generator.state, "torch_rng": torch.get_rng_state()}


def _restore(state: dict, net, opt, sched, gen: torch.Generator, sampler: ClipSampler) -> tuple:
    """Load ``state`` (from ``_state``) into the loop's objects; returns (step, seconds, history, points, ema)."""
    net.load_state_dict(state["net"])
    opt.load_state_dict(state["opt"])
    sched.load_state_dict(state["sched"])
    gen.set_state(state["gen"])
    sampler.rng.bit_generator.state = state["sampler"]
    torch.set_rng_state(state["torch_rng"])
    return state["step"], state["seconds"], list(state["history"]), list(state["points"]), state["ema"]
