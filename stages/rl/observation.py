"""What the policy observes, computed by ONE function in the world model and in the simulator.

The observation is the tokenizer's +-1 latent of the frame (both views, ``(bits, h, w)``) plus the
instruction's 384-d MiniLM embedding. In the world-model env the latent comes from the predicted
tokens; in the simulator the rendered views are first encoded by the same tokenizer, so a policy
trained in the world model meets the same kind of input in the simulator (docs/rl.md says why
latents rather than decoded RGB).
"""
from __future__ import annotations

from typing import Sequence

import gymnasium as gym
import numpy as np
import torch

TEXT_DIM = 384


class ObservationFn:
    """tokens (or rendered views) + instructions -> ``{"codes": (B, bits, h, w), "instruction": (B, 384)}``."""

    def __init__(self, tokenizer, text_embeddings: dict[str, Sequence[float]]):
        self.tok = tokenizer
        self._text = {k: np.asarray(v, dtype=np.float32) for k, v in text_embeddings.items()}
        h, w = tokenizer.grid
        self.space = gym.spaces.Dict({
            "codes": gym.spaces.Box(-1.0, 1.0, (tokenizer.bits, h, w), np.float32),
            "instruction": gym.spaces.Box(-np.inf, np.inf, (TEXT_DIM,), np.float32),
        })

    def text(self, instructions: Sequence[str]) -> np.ndarray:
        """(B, 384) embeddings; instructions never seen before are encoded with MiniLM once."""
        missing = sorted({s for s in instructions if s not in self._text})
        if missing:
            from stages.common.text_encoder import encode_texts

            for s, e in zip(missing, encode_texts(missing)):
                self._text[s] = np.asarray(e, dtype=np.float32)
        return np.stack([self._text[s] for s in instructions])

    def from_tokens(self, tokens, instructions: Sequence[str]) -> dict[str, np.ndarray]:
        """tokens (B, h, w) -> observation batch."""
        codes = self.tok.codes(torch.as_tensor(np.asarray(tokens, dtype=np.int64))).cpu().numpy().astype(np.float32)
        return {"codes": codes, "instruction": self.text(instructions)}

    def from_views(self, third: np.ndarray, wrist: np.ndarray, instructions: Sequence[str]) -> dict[str, np.ndarray]:
        """Rendered views (B, H, W, 3) uint8 -> tokens via the tokenizer -> the same observation."""
        return self.from_tokens(self.tok.encode(third, wrist).cpu(), instructions)


def index_obs(obs: dict[str, np.ndarray], i: int) -> dict[str, np.ndarray]:
    """Row ``i`` of an observation batch."""
    return {k: v[i] for k, v in obs.items()}
