"""What the policy observes, computed by ONE function in the world model and in the simulator.

    {"codes": (B, C, h, w)     the tokenizer's +-1 latent of the frame (both views): C = bits for
                               ``frame="current"`` (the frame now) or ``"first"`` (the episode's first,
                               real frame), 2 x bits for ``"both"`` (now, then first),
     "proprio": (B, 10)        TCP position, orientation and gripper opening (stages.common.proprio),
     "instruction": (B, 384)}  the instruction's MiniLM embedding

In the world-model env the latent comes from the predicted tokens and the proprioception from the
action world model's proprioception head; in the simulator the rendered views are first encoded by
the same tokenizer and the proprioception is read from the robot's state, then both go through the
same function (docs/rl.md says why latents rather than decoded RGB, docs/sft.md why proprioception).

``frame`` (``sft.frame``) says which frame's latent the policy reads. The first frame is the real
one in both places (the world model starts from it), so a policy that reads only the first frame and
proprioception acts on nothing the world model has to imagine but the arm's state (docs/sft.md).
Every caller passes ``first``, the episode's first-frame tokens, whatever the mode.
"""
from __future__ import annotations

from typing import Literal, Sequence

import gymnasium as gym
import numpy as np
import torch

from stages.common.proprio import PROPRIO_DIM

TEXT_DIM = 384
FRAMES = ("current", "first", "both")
Frame = Literal["current", "first", "both"]


class ObservationFn:
    """tokens (the frame now's and the episode's first) + proprioception + instructions -> the observation dict above."""

    def __init__(self, tokenizer, text_embeddings: dict[str, Sequence[float]], frame: Frame = "current"):
        if frame not in FRAMES:
            raise ValueError(f"unknown observed frame {frame!r}: expected one of {FRAMES}")
        self.tok, self.frame = tokenizer, frame
        self._text = {k: np.asarray(v, dtype=np.float32) for k, v in text_embeddings.items()}
        h, w = tokenizer.grid
        channels = tokenizer.bits * (2 if frame == "both" else 1)
        self.space = gym.spaces.Dict({
            "codes": gym.spaces.Box(-1.0, 1.0, (channels, h, w), np.float32),
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

    @classmethod
    def for_policy(cls, tokenizer, text_embeddings: dict[str, Sequence[float]], sft_info: dict) -> "ObservationFn":
        """The observation of the policy an sft artifact's ``policy.json`` describes (``frame`` absent: current)."""
        return cls(tokenizer, text_embeddings, sft_info.get("frame", "current"))

    def _codes(self, tokens) -> np.ndarray:
        return self.tok.codes(tokens).cpu().numpy().astype(np.float32)  # tokens: numpy or torch, any device

    def from_tokens(self, tokens, proprio, instructions: Sequence[str], first=None) -> dict[str, np.ndarray]:
        """tokens (B, h, w) of the frame now, proprio (B, 10), first (B, h, w) the episode's first frame's
        tokens (needed unless ``frame="current"``) -> observation batch."""
        if self.frame != "current" and first is None:
            raise ValueError(f"the policy observes the {self.frame!r} frame: pass the episode's first-frame tokens")
        if self.frame == "current":
            codes = self._codes(tokens)
        elif self.frame == "first":
            codes = self._codes(first)
        else:
            codes = np.concatenate([self._codes(tokens), self._codes(first)], axis=1)  # (B, 2 bits, h, w)
        if len(codes) != len(instructions):
            raise ValueError(f"{len(codes)} frames but {len(instructions)} instructions")
        proprio = np.asarray(proprio, dtype=np.float32).reshape(len(codes), PROPRIO_DIM)
        return {"codes": codes, "proprio": proprio, "instruction": self.text(instructions)}


def index_obs(obs: dict[str, np.ndarray], i: int) -> dict[str, np.ndarray]:
    """Row ``i`` of an observation batch."""
    return {k: v[i] for k, v in obs.items()}
