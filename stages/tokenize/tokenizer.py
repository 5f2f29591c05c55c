"""Public tokenizer API: load a trained tokenizer once, encode frames to tokens and decode back.

    tok = load_tokenizer(tokenize_artifact_dir, device="cpu")   # cached: one load per (dir, device)
    tokens = tok.encode(third, wrist)      # LongTensor (N, h, w); views uint8 (N, H, W, 3)
    third, wrist = tok.decode(tokens)      # float in [0, 1], each (N, 3, S, S)
    tok.codes(tokens)                      # FloatTensor (N, bits, h, w) of +-1 (a policy observation)
    tok.vocab_size, tok.grid, tok.bits, tok.image_size
"""
from __future__ import annotations

import functools
import os
import tempfile
from pathlib import Path

import numpy as np
import torch

from stages.tokenize.lfq import tokens_to_codes
from stages.tokenize.model import ModelSpec, TokenizerNet, from_obs, to_obs

CHECKPOINT = "tokenizer.pt"
FORMAT_VERSION = 1


class Tokenizer:
    """A trained tokenizer in eval mode; all methods run without autograd."""

    def __init__(self, net: TokenizerNet, device: str = "cpu"):
        self.net = net.to(device).eval().requires_grad_(False)
        self.device = device
        self.spec = net.spec

    @property
    def bits(self) -> int:
        return self.spec.bits

    @property
    def vocab_size(self) -> int:
        return 2**self.spec.bits

    @property
    def grid(self) -> tuple[int, int]:
        return self.spec.grid

    @property
    def image_size(self) -> int:
        return self.spec.image_size

    def _views(self, x) -> torch.Tensor:
        t = torch.from_numpy(np.ascontiguousarray(x)) if isinstance(x, np.ndarray) else torch.as_tensor(x)
        if t.dtype != torch.uint8:
            raise ValueError(f"tokenizer views must be uint8 (N, H, W, 3) images, got dtype {t.dtype}")
        return t.to(self.device)

    @torch.no_grad()
    def encode(self, third, wrist, batch_size: int = 256) -> torch.Tensor:
        """Token ids (N, h, w) int64 on the tokenizer's device for uint8 views (N, H, W, 3)."""
        third, wrist = self._views(third), self._views(wrist)
        out = [self.net.encode(to_obs(third[i : i + batch_size], wrist[i : i + batch_size], self.image_size)) for i in range(0, third.shape[0], batch_size)]
        return torch.cat(out) if out else torch.zeros((0, *self.grid), dtype=torch.int64, device=self.device)

    def _tokens(self, tokens) -> torch.Tensor:
        """Token ids as an int64 tensor on the device; accepts torch or numpy (e.g. TokenStore's uint16)."""
        if isinstance(tokens, np.ndarray):
            tokens = torch.from_numpy(tokens.astype(np.int64))
        return torch.as_tensor(tokens).to(self.device, torch.int64)

    @torch.no_grad()
    def codes(self, tokens) -> torch.Tensor:
        """The +-1 latent (N, bits, h, w) float32 of token ids (N, h, w)."""
        return tokens_to_codes(self._tokens(tokens), self.bits)

    @torch.no_grad()
    def decode(self, tokens, batch_size: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
        """(third, wrist), each (N, 3, S, S) float in [0, 1], from token ids (N, h, w)."""
        tokens = self._tokens(tokens)
        if tokens.dim() != 3 or tuple(tokens.shape[1:]) != self.grid:
            raise ValueError(f"tokens must have shape (N, {self.grid[0]}, {self.grid[1]}), got {tuple(tokens.shape)}")
        obs = [self.net.decode_codes(self.codes(tokens[i : i + batch_size])) for i in range(0, tokens.shape[0], batch_size)]
        obs = torch.cat(obs) if obs else torch.zeros((0, 6, self.image_size, self.image_size), device=self.device)
        return from_obs(obs)


def save_checkpoint(net: TokenizerNet, directory: str | Path) -> Path:
    """Write ``tokenizer.pt`` (spec + CPU weights) into ``directory`` atomically (temp file, then rename)."""
    directory = Path(directory)
    payload = {
        "format_version": FORMAT_VERSION,
        "spec": net.spec.to_dict(),
        "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()},
    }
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=".tokenizer-", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
        os.replace(tmp, directory / CHECKPOINT)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return directory / CHECKPOINT


def load_net(directory: str | Path) -> TokenizerNet:
    """The ``TokenizerNet`` saved in ``directory/tokenizer.pt`` (on CPU), with clear errors."""
    path = Path(directory) / CHECKPOINT
    if not path.is_file():
        raise FileNotFoundError(f"no tokenizer checkpoint at {path}: is {directory} a committed tokenize artifact?")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if payload.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{path}: checkpoint format_version {payload.get('format_version')!r}, this code reads {FORMAT_VERSION}")
    net = TokenizerNet(ModelSpec.from_dict(payload["spec"]))
    net.load_state_dict(payload["state_dict"])
    return net


@functools.lru_cache(maxsize=8)
def _load_cached(directory: str, device: str) -> Tokenizer:
    return Tokenizer(load_net(directory), device)


def load_tokenizer(directory: str | Path, device: str = "cpu") -> Tokenizer:
    """The tokenizer of a tokenize artifact, in eval mode; loaded from disk once per (dir, device)."""
    return _load_cached(str(Path(directory).resolve()), str(device))
