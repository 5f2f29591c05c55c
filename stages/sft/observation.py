"""What the policy observes, computed by ONE function in the world model and in the simulator.

    {"codes": (B, bits, h, w)  the tokenizer's +-1 latent of the frame (both views),
     "proprio": (B, 10)        TCP position, orientation and gripper opening (stages.common.proprio),
     "instruction": (B, 384)}  the instruction's MiniLM embedding

In the world-model env the latent comes from the predicted tokens and the proprioception from the
action world model's proprioception head; in the simulator the rendered views are first encoded by
the same tokenizer and the proprioception is read from the robot's state, then both go through the
same function (docs/rl.md says why latents rather than decoded RGB, docs/sft.md why proprioception).
"""
from __future__ import annotations

from typing import Sequence

import gymnasium as gym
import numpy as np
import torch

from stages.common.proprio import PROPRIO_DIM

TEXT_DIM = 384


class ObservationFn:
    """tokens (or rendered views) + proprioception + instructions -> the observation dict above."""

    def __init__(self, tokenizer, text_embeddings: dict[str, Sequence[float]]):
        self.tok = tokenizer
        self._text = {k: np.asarray(v, dtype=np.float32) for k, v in text_embeddings.items()}
        h, w = tokenizer.grid
        self.space = gym.spaces.Dict({
            "codes": gym.spaces.Box(-1.0, 1.0, (tokenizer.bits, h, w), np.float32),
            "proprio": gym.spaces.Box(-np.inf, np.inf, (PROPRIO_DIM,), np.float32),
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

    def from_tokens(self, tokens, proprio, instructions: Sequence[str]) -> dict[str, np.ndarray]:
        """tokens (B, h, w), proprio (B, 10) -> observation batch."""
        codes = self.tok.codes(tokens).cpu().numpy().astype(np.float32)  # tokens: numpy or torch, any device
        proprio = np.asarray(proprio, dtype=np.float32).reshape(len(codes), PROPRIO_DIM)
        return {"codes": codes, "proprio": proprio, "instruction": self.text(instructions)}

    def from_views(self, third: np.ndarray, wrist: np.ndarray, proprio, instructions: Sequence[str]) -> dict[str, np.ndarray]:
        """Rendered views (B, H, W, 3) uint8 -> tokens via the tokenizer -> the same observation."""
        return self.from_tokens(self.tok.encode(third, wrist).cpu(), proprio, instructions)


def index_obs(obs: dict[str, np.ndarray], i: int) -> dict[str, np.ndarray]:
    """Row ``i`` of an observation batch."""
    return {k: v[i] for k, v in obs.items()}
