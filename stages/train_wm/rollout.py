"""Batched world-model rollouts (used by goals and rl): load a checkpoint, reset, step.

```python
wm = load_world_model(train_wm_artifact_dir, kind="action", device="cpu")
roll = wm.rollout(batch_size=64)
roll.reset(tokens0)                  # (B, h, w) frame tokens; text WM: roll.reset(tokens0, text_emb (B, 384))
out = roll.step(actions)             # (B, 7) -> out.tokens (B, h, w), out.done_prob (B,), out.hidden (B, D)
roll.reset(tokens0[:2], env_ids=torch.tensor([3, 7]))   # restart some envs only (VecEnv auto-reset)
done = wm.done_for_sequences(tokens (B, T+1, h, w), actions (B, T, 7))   # (B, T) done prob of frames 1..T
proprio = wm.next_proprio(proprio (B, 10), actions (B, 7), out.tokens)     # action WM: the robot's next state
```

Context window policy: the temporal KV cache keeps the last ``spec.window`` clean frames (a ring
buffer); a longer episode drops the oldest frame's keys/values. Cached keys of the kept frames are
not recomputed, so past ``window`` frames the rollout is an approximation of attending to a
``window``-frame clip (exact up to ``window`` frames). Rotary temporal positions make the relative
offsets always ones seen in training.

Actions are clipped per dimension to the training data's [min, max] (stored in the checkpoint);
``Rollout.clip_count`` counts clipped action entries, NaN/inf actions raise ``ValueError``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from stages.train_wm.model import TEXT_DIM, TemporalCache, WMSpec, WorldModelNet, cosine_mask_count

CHECKPOINTS = {"action": "action_wm.pt", "text": "text_wm.pt"}
TEXT_EMBEDDINGS = "text_embeddings.json"


@dataclass
class StepOutput:
    tokens: torch.Tensor  # (B, h, w) long: the predicted next frame
    done_prob: torch.Tensor  # (B,) done-head probability of the predicted frame
    hidden: torch.Tensor  # (B, D) pooled head features of the predicted frame


def save_world_model(net: WorldModelNet, path: Path, extra: dict | None = None) -> None:
    """Write a checkpoint (spec, weights incl. action stats, extra metadata) to ``path`` via a temp file."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save({"spec": net.spec.to_dict(), "state_dict": net.state_dict(), "extra": extra or {}}, tmp)
    tmp.replace(path)


def _load_checkpoint(path: Path, device: str) -> tuple[WorldModelNet, dict]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no world-model checkpoint at {path}: is its directory a committed train_wm artifact?")
    ck = torch.load(path, map_location=device, weights_only=True)
    net = WorldModelNet(WMSpec.from_dict(ck["spec"])).to(device)
    net.load_state_dict(ck["state_dict"])
    return net.eval(), ck.get("extra", {})


def load_net(path: Path, device: str = "cpu") -> WorldModelNet:
    """The network stored at ``path`` (eval mode, on ``device``)."""
    return _load_checkpoint(path, device)[0]


class WorldModel:
    """A trained world model ready for rollouts, with its settings for decoding."""

    def __init__(self, net: WorldModelNet, decode_steps: int = 2, temperature: float = 0.0,
                 text_embeddings: dict[str, list[float]] | None = None, proprio_head=None):
        if decode_steps < 1:
            raise ValueError(f"decode_steps must be >= 1, got {decode_steps}")
        self.net, self.decode_steps, self.temperature = net.eval(), decode_steps, temperature
        self.spec = net.spec
        self._text = text_embeddings or {}
        self.proprio_head = proprio_head  # stages.train_wm.proprio.ProprioHead (action WM only)

    @torch.no_grad()
    def next_proprio(self, proprio: torch.Tensor, actions: torch.Tensor, next_tokens: torch.Tensor) -> torch.Tensor:
        """The robot's next proprioception (B, 10) after ``actions`` (B, 7) led to frame ``next_tokens`` (B, h, w)."""
        if self.proprio_head is None:
            raise RuntimeError("this world model has no proprioception head (train_wm artifact without proprio_head.pt)")
        from stages.tokenize.lfq import tokens_to_codes

        codes = tokens_to_codes(next_tokens.to(self.device, torch.int64), self.proprio_head.bits)  # (B, bits, h, w)
        return self.proprio_head(proprio.to(self.device, torch.float32), actions.to(self.device, torch.float32), codes)

    @property
    def device(self) -> torch.device:
        return self.net.pos_emb.device

    def text_embedding(self, instructions: list[str]) -> torch.Tensor:
        """Instruction embeddings (B, 384): cached in the artifact, else encoded with MiniLM."""
        missing = [s for s in instructions if s not in self._text]
        if missing:
            from stages.common.text_encoder import encode_texts

            for s, e in zip(missing, encode_texts(missing)):
                self._text[s] = e.tolist()
        return torch.tensor([self._text[s] for s in instructions], dtype=torch.float32, device=self.device)

    def rollout(self, batch_size: int, seed: int = 0, cache_dtype: torch.dtype = torch.float32) -> "Rollout":
        """``batch_size`` envs; ``cache_dtype`` bfloat16 only for callers that step it under bf16 autocast
        (the attention reads the cache in bf16 there anyway: the same results without a cast per step)."""
        return Rollout(self, batch_size, seed, cache_dtype)

    @torch.no_grad()
    def done_for_sequences(self, tokens: torch.Tensor, control: torch.Tensor) -> torch.Tensor:
        """Done probabilities (B, T) of real frames 1..T, teacher-forced through the rollout path.

        tokens (B, T+1, h, w); control: actions (B, T, 7) for the action WM, embeddings (B, 384) for text.
        """
        b, t1 = tokens.shape[:2]
        roll = self.rollout(b)
        if self.spec.kind == "action":
            roll.reset(tokens[:, 0])
            outs = [roll.step(control[:, i], next_tokens=tokens[:, i + 1]).done_prob for i in range(t1 - 1)]
        else:
            roll.reset(tokens[:, 0], control)
            outs = [roll.step(next_tokens=tokens[:, i + 1]).done_prob for i in range(t1 - 1)]
        return torch.stack(outs, 1)


def load_world_model(artifact_dir: str | Path, kind: str = "action", device: str = "cpu",
                     decode_steps: int | None = None, temperature: float | None = None) -> WorldModel:
    """The ``kind`` ("action" | "text") world model of a train_wm artifact, with its decoding settings."""
    if kind not in CHECKPOINTS:
        raise ValueError(f"kind must be one of {sorted(CHECKPOINTS)}, got {kind!r}")
    artifact_dir = Path(artifact_dir)
    path = artifact_dir / CHECKPOINTS[kind]
    net, extra = _load_checkpoint(path, device)
    emb_path = artifact_dir / TEXT_EMBEDDINGS
    text = json.loads(emb_path.read_text()) if emb_path.is_file() else {}
    head = None
    if kind == "action":
        from stages.train_wm.proprio import CHECKPOINT as PROPRIO_CHECKPOINT, load_head

        if (artifact_dir / PROPRIO_CHECKPOINT).is_file():
            head = load_head(artifact_dir / PROPRIO_CHECKPOINT, device)
    return WorldModel(net,
                      decode_steps=decode_steps if decode_steps is not None else int(extra.get("decode_steps", 2)),
                      temperature=temperature if temperature is not None else float(extra.get("temperature", 0.0)),
                      text_embeddings=text, proprio_head=head)


class Rollout:
    """``batch_size`` environments stepping one world model with a shared temporal KV cache."""

    def __init__(self, wm: WorldModel, batch_size: int, seed: int = 0, cache_dtype: torch.dtype = torch.float32):
        spec = wm.spec
        self.wm, self.net, self.spec, self.batch = wm, wm.net, spec, batch_size
        dev = wm.device
        self.cache = TemporalCache(spec.depth, batch_size, spec.tokens, spec.heads, spec.dim // spec.heads,
                                   spec.window, dev, cache_dtype)
        self.frame = torch.zeros(batch_size, spec.tokens, dtype=torch.long, device=dev)  # (B, N) latest frame
        self.text_kv: list | None = None
        self.text_mem: torch.Tensor | None = None  # (B, 1, M, D)
        self.clip_count = 0  # clipped action entries since creation
        self.last_clip_count = 0  # clipped action entries in the last step
        self.gen = torch.Generator(device=dev).manual_seed(seed)
        self._ready = torch.zeros(batch_size, dtype=torch.bool)

    def _check_tokens(self, tokens: torch.Tensor, n: int) -> torch.Tensor:
        h, w = self.spec.grid
        if tuple(tokens.shape) != (n, h, w):
            raise ValueError(f"expected frame tokens of shape ({n}, {h}, {w}), got {tuple(tokens.shape)}")
        tokens = tokens.to(self.wm.device, torch.long).reshape(n, h * w).clone()  # never alias the caller's tensor
        if int(tokens.min()) < 0 or int(tokens.max()) >= self.spec.vocab_size:
            raise ValueError(f"frame tokens must lie in [0, {self.spec.vocab_size}), got "
                             f"[{int(tokens.min())}, {int(tokens.max())}]")
        return tokens

    @torch.no_grad()
    def reset(self, tokens0: torch.Tensor, control: torch.Tensor | None = None,
              env_ids: torch.Tensor | None = None) -> None:
        """Start episodes from frame tokens (n, h, w); text WM also needs instruction embeddings (n, 384).

        Without ``env_ids`` all ``batch_size`` envs restart; with it (n,) only those envs do.
        """
        n = self.batch if env_ids is None else len(env_ids)
        tokens0 = self._check_tokens(torch.as_tensor(tokens0), n)
        if self.spec.kind == "text":
            if control is None:
                raise ValueError("the text world model needs instruction embeddings (n, 384) at reset")
            control = torch.as_tensor(control, dtype=torch.float32, device=self.wm.device)
            if tuple(control.shape) != (n, TEXT_DIM):
                raise ValueError(f"expected text embeddings of shape ({n}, {TEXT_DIM}), got {tuple(control.shape)}")
            mem = self.net.memory(control)  # (n, 1, M, D)
            if env_ids is None or self.text_mem is None:
                if env_ids is not None:
                    raise ValueError("reset all envs of a text rollout once before resetting a subset")
                self.text_mem = mem
            else:
                self.text_mem[env_ids] = mem
            self.text_kv = self.net.memory_kv(self.text_mem, 1)
        elif control is not None:
            raise ValueError("the action world model takes actions in step(), not a control at reset")
        if env_ids is None:
            self.cache.reset()
            self.frame = tokens0
            self._ready[:] = True
        else:
            env_ids = torch.as_tensor(env_ids, dtype=torch.long, device=self.wm.device)
            self.cache.reset(env_ids)
            self.frame[env_ids] = tokens0
            self._ready[env_ids.cpu()] = True

    def _clip(self, actions: torch.Tensor) -> torch.Tensor:
        actions = torch.as_tensor(actions, dtype=torch.float32, device=self.wm.device)
        if tuple(actions.shape) != (self.batch, 7):
            raise ValueError(f"expected actions of shape ({self.batch}, 7), got {tuple(actions.shape)}")
        if not bool(torch.isfinite(actions).all()):
            bad = (~torch.isfinite(actions)).nonzero()[:, 0].unique().tolist()
            raise ValueError(f"actions contain NaN or inf (envs {bad}); the world model only accepts finite actions")
        lo, hi = self.net.action_low, self.net.action_high
        clipped = (actions < lo) | (actions > hi)
        self.last_clip_count = int(clipped.sum())
        self.clip_count += self.last_clip_count
        return torch.minimum(torch.maximum(actions, lo), hi)

    # Eq. 1 in imagination: one new frame and done signal per env, temporal attention KV-cached
    @torch.no_grad()
    def step(self, actions: torch.Tensor | None = None, next_tokens: torch.Tensor | None = None) -> StepOutput:
        """Advance every env one frame. actions (B, 7) for the action WM, None for the text WM.

        With ``next_tokens`` (B, h, w) the next frame is given (teacher forcing) and only the done head
        and hidden state are computed.
        """
        if not bool(self._ready.all()):
            raise RuntimeError(f"reset() envs {(~self._ready).nonzero()[:, 0].tolist()} before step()")
        net, b, n = self.net, self.batch, self.spec.tokens
        if self.spec.kind == "action":
            if actions is None:
                raise ValueError("the action world model needs actions (B, 7) in step()")
            kv = net.memory_kv(net.memory(self._clip(actions)[:, None]), 1)
        else:
            if actions is not None:
                raise ValueError("the text world model takes no actions; pass the instruction at reset()")
            kv = self.text_kv
        ctx = net.backbone(self.frame[:, None], None, cache=self.cache, kv=kv).view(b, n, -1)  # (B, N, D)
        self.cache.step += 1
        if next_tokens is None:
            nxt = self._decode(ctx)
        else:
            nxt = self._check_tokens(torch.as_tensor(next_tokens), b)
        done, hidden = net.done_logit(net.head(ctx, nxt))
        self.frame = nxt
        h, w = self.spec.grid
        return StepOutput(nxt.view(b, h, w), torch.sigmoid(done), hidden)

    def _decode(self, ctx: torch.Tensor) -> torch.Tensor:
        """MaskGIT decoding of the next frame in ``decode_steps`` passes. ctx (B, N, D) -> tokens (B, N)."""
        net, steps, temp = self.net, self.wm.decode_steps, self.wm.temperature
        b, n = ctx.shape[:2]
        tok = torch.full((b, n), net.mask_id, dtype=torch.long, device=ctx.device)
        for s in range(steps):
            feats = net.head(ctx, tok)  # (B, N, D)
            hidden = tok == net.mask_id  # (B, N); the same count of hidden tokens in every env
            keep_hidden = cosine_mask_count(n, s, steps)
            if keep_hidden == 0 and temp == 0:
                # last greedy pass: logits of the still-hidden tokens only, no confidences needed
                idx = hidden.nonzero()[:, 1].view(b, -1)  # (B, K)
                pred = net.logits(feats.gather(1, idx[..., None].expand(-1, -1, feats.shape[-1]))).argmax(-1)
                return tok.scatter(1, idx, pred)
            logits = net.logits(feats)  # (B, N, V)
            if temp > 0:
                probs = torch.softmax(logits / temp, -1)
                pred = torch.multinomial(probs.view(-1, probs.shape[-1]), 1, generator=self.gen).view(b, n)
                conf = probs.gather(-1, pred[..., None])[..., 0]
            else:
                conf, pred = torch.softmax(logits, -1).max(-1)
            pred = torch.where(hidden, pred, tok)
            if keep_hidden == 0:
                return pred
            conf = torch.where(hidden, conf, torch.full_like(conf, float("inf")))
            # reveal the most confident tokens; the keep_hidden least confident stay masked
            order = conf.argsort(-1)  # ascending
            still = torch.zeros_like(hidden).scatter_(1, order[:, :keep_hidden], True)
            tok = torch.where(still, torch.full_like(pred, net.mask_id), pred)
        return tok
