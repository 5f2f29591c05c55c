"""The world-model network: a spatial-temporal transformer over frame tokens with a MaskGIT head.

Backbone (``depth`` blocks of [spatial attention within a frame, causal temporal attention per
spatial position, cross-attention to the control signal, MLP]) reads the clean tokens of frames
0..t and the control of frame t and produces a context ``c_t`` (one vector per spatial position).
A small MaskGIT head (``head_depth`` blocks of [spatial attention, MLP]) reads ``c_t`` plus the
partially revealed tokens of frame t+1 and predicts logits over the vocabulary for frame t+1.
The done head reads the head's features when frame t+1 is fully revealed (its "current frame").

Why this split: the temporal KV cache holds only clean frames, so it is exact, and each decoding
pass of a new frame re-runs only the small head, not the whole backbone. Temporal attention uses
rotary position embeddings, so a sliding context window only ever sees relative offsets that
occurred in training.

Controls: ``action`` = an MLP over the 7-d normalised delta-EE action, producing
``control_tokens`` memory tokens per frame; ``text`` = a linear projection of ALL 384 dims of the
MiniLM instruction embedding into ``control_tokens`` memory tokens (constant over the episode).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

ACTION_DIM = 7
TEXT_DIM = 384


@dataclass(frozen=True)
class WMSpec:
    """Architecture of one world model (stored in the checkpoint)."""

    kind: str  # "action" | "text"
    vocab_size: int
    grid: tuple[int, int]  # (h, w) tokens per frame
    dim: int = 128
    depth: int = 4
    heads: int = 4
    head_depth: int = 1
    mlp_ratio: int = 4
    window: int = 16  # frames of temporal context
    control_tokens: int = 4
    # control steps of the simulator per world-model step (stages.common.frame_skip); not architecture,
    # but what one step means, so every consumer of the checkpoint reads it from here
    frame_skip: int = 1

    def __post_init__(self):
        if self.kind not in ("action", "text"):
            raise ValueError(f"world model kind must be 'action' or 'text', got {self.kind!r}")
        if self.dim % self.heads or (self.dim // self.heads) % 2:
            raise ValueError(f"dim={self.dim} must split into {self.heads} heads of even size (rotary embedding)")
        if self.frame_skip < 1:
            raise ValueError(f"frame_skip must be >= 1, got {self.frame_skip}")

    @property
    def tokens(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def control_dim(self) -> int:
        return ACTION_DIM if self.kind == "action" else TEXT_DIM

    def to_dict(self) -> dict:
        d = asdict(self)
        d["grid"] = list(self.grid)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "WMSpec":
        return cls(**{**d, "grid": tuple(d["grid"])})


def rotary(x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """Rotary position embedding of ``x`` (..., T, hd) at positions ``pos`` (T,) (rotate-half layout)."""
    half = x.shape[-1] // 2
    freqs = 1.0 / (10000.0 ** (torch.arange(half, device=x.device, dtype=torch.float32) / half))  # (hd/2,)
    ang = pos.to(torch.float32)[:, None] * freqs[None]  # (T, hd/2)
    cos, sin = ang.cos(), ang.sin()
    x1, x2 = x[..., :half], x[..., half:]
    return torch.cat((x1 * cos - x2 * sin, x1 * sin + x2 * cos), dim=-1)


class SelfAttention(nn.Module):
    """Multi-head self-attention with one fused QKV projection over (S, L, D) sequences."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def qkv_heads(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(S, L, D) -> q, k, v each (S, H, L, hd)."""
        s, l, d = x.shape
        qkv = self.qkv(x).view(s, l, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        return qkv[0], qkv[1], qkv[2]

    def merge(self, y: torch.Tensor) -> torch.Tensor:
        """(S, H, L, hd) -> projected (S, L, D)."""
        s, h, l, hd = y.shape
        return self.proj(y.transpose(1, 2).reshape(s, l, h * hd))

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (S, L, D) -> (S, L, D)
        q, k, v = self.qkv_heads(x)
        return self.merge(F.scaled_dot_product_attention(q, k, v))


class CrossAttention(nn.Module):
    """Frame tokens attend to the control memory tokens of their own frame."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.proj = nn.Linear(dim, dim)

    def memory_kv(self, mem: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, M, D) control memory -> k, v each (S, H, M, hd)."""
        s, m, d = mem.shape
        kv = self.kv(mem).view(s, m, 2, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        return kv[0], kv[1]

    def forward(self, x: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """x (S, N, D) queries, k/v (S, H, M, hd) -> (S, N, D)."""
        s, n, d = x.shape
        q = self.q(x).view(s, n, self.heads, d // self.heads).transpose(1, 2)
        y = F.scaled_dot_product_attention(q, k, v)  # (S, H, N, hd)
        return self.proj(y.transpose(1, 2).reshape(s, n, d))


def mlp(dim: int, ratio: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(dim, ratio * dim), nn.GELU(), nn.Linear(ratio * dim, dim))


class TemporalCache:
    """Per-layer ring buffers of temporal keys/values of clean frames, shared slot index for all envs.

    Every env writes its frame of global step ``s`` into slot ``s % window``. An env reset at step
    ``start[b]`` masks out slots written before it. Rotary positions use the global step: attention
    only depends on relative offsets, so envs reset at different steps need no re-indexing.
    """

    def __init__(self, depth: int, batch: int, tokens: int, heads: int, hd: int, window: int, device, dtype):
        shape = (batch * tokens, heads, window, hd)
        self.k = [torch.zeros(shape, device=device, dtype=dtype) for _ in range(depth)]
        self.v = [torch.zeros(shape, device=device, dtype=dtype) for _ in range(depth)]
        self.window, self.batch, self.tokens = window, batch, tokens
        self.step = 0  # global step of the next frame to write
        self.start = torch.zeros(batch, dtype=torch.long, device=device)  # first valid step per env

    def reset(self, env_ids: torch.Tensor | None = None) -> None:
        if env_ids is None:
            self.step = 0
            self.start.zero_()
        else:
            self.start[env_ids] = self.step

    def attn_mask(self) -> tuple[int, torch.Tensor | None]:
        """Slots to attend over (after writing the current step) and a boolean mask when envs differ.

        Returns (L, mask) where mask is None or (B*N, 1, 1, L) with True = attend.
        """
        s = self.step
        length = min(s + 1, self.window)
        if bool((self.start == self.start[0]).all()) and int(self.start[0]) <= s + 1 - length:
            return length, None
        slots = torch.arange(length, device=self.start.device)
        # global step held by each slot: the latest step <= s congruent to the slot index
        held = s - ((s - slots) % self.window)  # (L,)
        valid = held[None, :] >= self.start[:, None]  # (B, L)
        mask = valid[:, None, :].expand(self.batch, self.tokens, length).reshape(-1, 1, 1, length)
        return length, mask


class Block(nn.Module):
    """[spatial self-attention, causal temporal self-attention, control cross-attention, MLP], pre-norm."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int):
        super().__init__()
        self.n1, self.spatial = nn.LayerNorm(dim), SelfAttention(dim, heads)
        self.n2, self.temporal = nn.LayerNorm(dim), SelfAttention(dim, heads)
        self.n3, self.cross = nn.LayerNorm(dim), CrossAttention(dim, heads)
        self.n4, self.mlp = nn.LayerNorm(dim), mlp(dim, mlp_ratio)

    def temporal_full(self, x: torch.Tensor) -> torch.Tensor:
        """Causal attention over all T frames. x (B, T, N, D) -> (B, T, N, D)."""
        b, t, n, d = x.shape
        xs = x.permute(0, 2, 1, 3).reshape(b * n, t, d)
        q, k, v = self.temporal.qkv_heads(xs)
        pos = torch.arange(t, device=x.device)
        q, k = rotary(q, pos), rotary(k, pos)
        y = self.temporal.merge(F.scaled_dot_product_attention(q, k, v, is_causal=True))  # (B*N, T, D)
        return y.view(b, n, t, d).permute(0, 2, 1, 3)

    def temporal_step(self, x: torch.Tensor, cache: TemporalCache, layer: int) -> torch.Tensor:
        """One new frame attending over cached frames. x (B, 1, N, D) -> (B, 1, N, D)."""
        b, _, n, d = x.shape
        h = self.temporal.heads
        qkv = self.temporal.qkv(x.reshape(b * n, d)).view(b * n, 3, h, d // h)
        qk = rotary(qkv[:, :2, :, None], torch.tensor([cache.step], device=x.device))  # (B*N, 2, H, 1, hd)
        q, v = qk[:, 0], qkv[:, 2]  # (B*N, H, 1, hd), (B*N, H, hd)
        slot = cache.step % cache.window
        cache.k[layer][:, :, slot] = qk[:, 1, :, 0]
        cache.v[layer][:, :, slot] = v
        length, mask = cache.attn_mask()
        # one query per sequence: plain batched matmuls measured ~2x faster than SDPA's CPU kernel here
        scores = torch.matmul(q, cache.k[layer][:, :, :length].transpose(-1, -2)) * q.shape[-1] ** -0.5
        if mask is not None:
            scores = scores.masked_fill(~mask, float("-inf"))
        y = torch.matmul(scores.softmax(-1), cache.v[layer][:, :, :length])  # (B*N, H, 1, hd)
        return self.temporal.merge(y).view(b, 1, n, d)

    def forward(self, x: torch.Tensor, mem_k: torch.Tensor, mem_v: torch.Tensor,
                cache: TemporalCache | None = None, layer: int = 0) -> torch.Tensor:
        """x (B, T, N, D); mem_k/mem_v (B*T, H, M, hd) -> (B, T, N, D). With a cache, T must be 1."""
        b, t, n, d = x.shape
        x = x + self.spatial(self.n1(x).view(b * t, n, d)).view(b, t, n, d)
        if cache is None:
            x = x + self.temporal_full(self.n2(x))
        else:
            x = x + self.temporal_step(self.n2(x), cache, layer)
        x = x + self.cross(self.n3(x).view(b * t, n, d), mem_k, mem_v).view(b, t, n, d)
        return x + self.mlp(self.n4(x))


class HeadBlock(nn.Module):
    """[spatial self-attention, MLP] over one frame, pre-norm."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int):
        super().__init__()
        self.n1, self.attn = nn.LayerNorm(dim), SelfAttention(dim, heads)
        self.n2, self.mlp = nn.LayerNorm(dim), mlp(dim, mlp_ratio)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (S, N, D) -> (S, N, D)
        x = x + self.attn(self.n1(x))
        return x + self.mlp(self.n2(x))


class WorldModelNet(nn.Module):
    """Next-frame token model conditioned on actions or on an instruction embedding, with a done head."""

    def __init__(self, spec: WMSpec):
        super().__init__()
        self.spec = spec
        d, m = spec.dim, spec.control_tokens
        self.mask_id = spec.vocab_size
        self.tok_emb = nn.Embedding(spec.vocab_size, d)
        self.pos_emb = nn.Parameter(torch.randn(spec.tokens, d) * 0.02)
        if spec.kind == "action":
            self.control = nn.Sequential(nn.Linear(ACTION_DIM, d), nn.GELU(), nn.Linear(d, m * d))
        else:
            self.control = nn.Linear(TEXT_DIM, m * d)
        self.control_pos = nn.Parameter(torch.randn(m, d) * 0.02)
        self.control_norm = nn.LayerNorm(d)
        self.blocks = nn.ModuleList(Block(d, spec.heads, spec.mlp_ratio) for _ in range(spec.depth))
        self.ctx_norm = nn.LayerNorm(d)
        self.head_emb = nn.Embedding(spec.vocab_size + 1, d)  # + mask token
        self.head_blocks = nn.ModuleList(HeadBlock(d, spec.heads, spec.mlp_ratio) for _ in range(spec.head_depth))
        self.head_norm = nn.LayerNorm(d)
        self.logits = nn.Linear(d, spec.vocab_size)
        self.done_head = nn.Sequential(nn.Linear(d, d), nn.GELU(), nn.Linear(d, 1))
        # action normalisation and clip range, fitted on the training data (saved with the weights)
        self.register_buffer("action_low", -torch.ones(ACTION_DIM))
        self.register_buffer("action_high", torch.ones(ACTION_DIM))
        self.register_buffer("action_mean", torch.zeros(ACTION_DIM))
        self.register_buffer("action_std", torch.ones(ACTION_DIM))
        self.apply(self._init)

    @staticmethod
    def _init(mod: nn.Module) -> None:
        if isinstance(mod, nn.Linear):
            nn.init.normal_(mod.weight, std=0.02)
            nn.init.zeros_(mod.bias)
        elif isinstance(mod, nn.Embedding):
            nn.init.normal_(mod.weight, std=0.02)

    def set_action_stats(self, actions: torch.Tensor) -> None:
        """Fit clip range and normalisation from training actions (K, 7)."""
        self.action_low.copy_(actions.min(0).values)
        self.action_high.copy_(actions.max(0).values)
        self.action_mean.copy_(actions.mean(0))
        self.action_std.copy_(actions.std(0).clamp_min(1e-3))

    def memory(self, control: torch.Tensor) -> torch.Tensor:
        """Control memory tokens. action (B, T, 7) -> (B, T, M, D); text (B, 384) -> (B, 1, M, D)."""
        if self.spec.kind == "action":
            control = (control - self.action_mean) / self.action_std
        else:
            control = control[:, None]
        b, t = control.shape[:2]
        mem = self.control(control).view(b, t, self.spec.control_tokens, self.spec.dim)
        return self.control_norm(mem + self.control_pos)

    def memory_kv(self, mem: torch.Tensor, t: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per-layer cross-attention k/v (B*T, H, M, hd) from memory (B, T or 1, M, D), broadcast to T frames."""
        b, tm, m, d = mem.shape
        out = []
        for blk in self.blocks:
            k, v = blk.cross.memory_kv(mem.reshape(b * tm, m, d))
            if tm != t:  # text memory is shared by every frame
                k = k.view(b, 1, *k.shape[1:]).expand(b, t, *k.shape[1:]).reshape(b * t, *k.shape[1:])
                v = v.view(b, 1, *v.shape[1:]).expand(b, t, *v.shape[1:]).reshape(b * t, *v.shape[1:])
            out.append((k, v))
        return out

    def backbone(self, tokens: torch.Tensor, control: torch.Tensor,
                 cache: TemporalCache | None = None, kv: list | None = None) -> torch.Tensor:
        """Context for predicting the next frame. tokens (B, T, N) clean; control see ``memory``.

        Returns (B, T, N, D). With ``cache`` (T == 1) the frame is appended to the temporal cache;
        ``kv`` may pass precomputed cross-attention k/v (see ``memory_kv``).
        """
        b, t, n = tokens.shape
        x = self.tok_emb(tokens) + self.pos_emb  # (B, T, N, D)
        if kv is None:
            kv = self.memory_kv(self.memory(control), t)
        for i, blk in enumerate(self.blocks):
            x = blk(x, kv[i][0], kv[i][1], cache, i)
        return self.ctx_norm(x)

    def head(self, ctx: torch.Tensor, next_tokens: torch.Tensor) -> torch.Tensor:
        """Head features of the next frame. ctx (S, N, D); next_tokens (S, N) with mask_id -> (S, N, D)."""
        x = self.head_emb(next_tokens) + self.pos_emb + ctx
        for blk in self.head_blocks:
            x = blk(x)
        return self.head_norm(x)

    def done_logit(self, feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Done logit (S,) and pooled hidden state (S, D) from head features (S, N, D) of a clean frame."""
        pooled = feats.mean(1)
        return self.done_head(pooled).squeeze(-1), pooled

    # Eq. 1: next-frame tokens and done signal from frames 0..t and the control
    def forward(self, tokens: torch.Tensor, control: torch.Tensor, mask: torch.Tensor,
                context: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Teacher-forced training pass over a clip.

        tokens (B, T+1, N) clean; control (B, T, 7) actions or (B, 384) text; mask (B, T, N) bool, True
        where a target token of frames 1..T is hidden; ``context`` (B, T, N) replaces frames 0..T-1 as the
        backbone's input (e.g. noised, ``data.corrupt_context``), targets stay ``tokens[:, 1:]``.
        Returns logits (B, T, N, V) and done logits (B, T) of frames 1..T.
        """
        b, t1, n = tokens.shape
        t = t1 - 1
        context = tokens[:, :t] if context is None else context
        if tuple(context.shape) != (b, t, n):
            raise ValueError(f"context must be (B, T, N) = {(b, t, n)}, got {tuple(context.shape)}")
        ctx = self.backbone(context, control).reshape(b * t, n, -1)
        target = tokens[:, 1:].reshape(b * t, n)
        masked = torch.where(mask.reshape(b * t, n), torch.full_like(target, self.mask_id), target)
        logits = self.logits(self.head(ctx, masked)).view(b, t, n, -1)
        done, _ = self.done_logit(self.head(ctx, target))
        return logits, done.view(b, t)


def matmul_flops_per_step(spec: WMSpec, batch: int, context: int, decode_steps: int) -> float:
    """Matmul FLOPs of one rollout step (backbone on 1 frame, ``decode_steps`` head passes + 1 clean pass).

    ``context`` = frames the temporal attention attends over. Counts 2*m*n*k per matmul (linear
    layers, attention scores and weighted sums, logits); ignores norms, softmax and elementwise ops.
    """
    d, n, m, r = spec.dim, spec.tokens, spec.control_tokens, spec.mlp_ratio
    tok = batch * n
    per_block = (
        tok * 2 * d * 3 * d + tok * 2 * 2 * n * d + tok * 2 * d * d  # spatial: qkv, scores+sum, proj
        + tok * 2 * d * 3 * d + tok * 2 * 2 * context * d + tok * 2 * d * d  # temporal
        + tok * 2 * d * d + batch * m * 2 * d * 2 * d + tok * 2 * 2 * m * d + tok * 2 * d * d  # cross
        + tok * 2 * 2 * d * r * d  # mlp
    )
    control = batch * (2 * ACTION_DIM * d + 2 * d * m * d) if spec.kind == "action" else 0
    head_block = tok * 2 * d * 3 * d + tok * 2 * 2 * n * d + tok * 2 * d * d + tok * 2 * 2 * d * r * d
    passes = decode_steps + 1
    head = passes * spec.head_depth * head_block + decode_steps * tok * 2 * d * spec.vocab_size
    done = batch * (2 * d * d + 2 * d)
    return float(spec.depth * per_block + control + head + done)


def cosine_mask_count(n: int, step: int, steps: int) -> int:
    """MaskGIT cosine schedule: tokens still hidden after decoding pass ``step`` (0-based) of ``steps``."""
    return int(math.floor(n * math.cos(math.pi / 2 * (step + 1) / steps)))
