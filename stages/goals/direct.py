"""The direct goal predictor (ablation of the text world model's imagined goal, beyond the paper).

One MaskGIT "jump": a text-conditioned network of the world model's architecture
(``stages.train_wm.model.WorldModelNet``, kind ``text``) trained on two-frame clips (an early frame
of a successful IND training episode, that episode's last frame) with the episode's instruction.
Predicting the end state in one step sidesteps what makes the text WM copy its input: rolled out a
frame at a time, with no action and no motion yet in its context, the most likely next frame is the
current one.
"""
from __future__ import annotations

import numpy as np
import torch

from stages.train_wm.data import ClipSampler, Episode
from stages.train_wm.model import WMSpec, WorldModelNet
from stages.train_wm.rollout import WorldModel
from stages.train_wm.train import train_world_model

EARLY = (0.0, 0.125, 0.25)  # fractions of an episode whose frames are paired with its last frame


def jump_clips(store, episodes: list, early: tuple = EARLY) -> list[Episode]:
    """(frame at each fraction of ``early``, last frame) of each episode as one-step clips.

    episodes: collect ``EpisodeMeta`` of successful episodes; store: the tokenize ``TokenStore``.
    """
    clips = []
    for m in episodes:
        tokens = np.asarray(store.episode(m.episode_id), dtype=np.int64)
        tokens = tokens.reshape(len(tokens), -1)  # (T+1, N)
        for f in early:
            t = int(f * (len(tokens) - 1))
            clips.append(Episode(f"{m.episode_id}@{t}", m.instruction, m.split, np.stack([tokens[t], tokens[-1]]),
                                 np.zeros((1, 7), np.float32), np.array([0.0, 1.0], np.float32),
                                 np.zeros((2, 10), np.float32), m.kind))
    return clips


def train_goal_predictor(clips: list[Episode], text_emb: dict[str, np.ndarray], *, vocab: int, grid: tuple[int, int],
                         dim: int, depth: int, steps: int, batch_size: int, lr: float, seed: int, device: str,
                         progress=None) -> tuple[WorldModelNet, dict]:
    """Fit the jump network (token cross-entropy only: every target frame is a success)."""
    torch.manual_seed(seed)
    spec = WMSpec(kind="text", vocab_size=vocab, grid=grid, dim=dim, depth=depth, heads=4, window=2)
    net = WorldModelNet(spec).to(device)
    sampler = ClipSampler(clips, 1, text_emb, seed)
    result = train_world_model(net, sampler, steps=steps, batch_size=batch_size, lr=lr, weight_decay=0.05,
                               done_weight=0.0, done_kind="bce", seed=seed, device=device, progress=progress)
    return net, result


@torch.no_grad()
def predict_goals(net: WorldModelNet, start: torch.Tensor, instructions: list[str], text_emb: dict,
                  decode_steps: int, batch_size: int = 64) -> np.ndarray:
    """Goal tokens (E, h, w) for start frames (E, h, w) and their instructions, greedy decoding."""
    wm = WorldModel(net, decode_steps, 0.0, {k: list(map(float, v)) for k, v in text_emb.items()})
    out = []
    for i in range(0, len(start), batch_size):
        s = start[i: i + batch_size]
        roll = wm.rollout(len(s))
        roll.reset(s, wm.text_embedding(instructions[i: i + batch_size]))
        out.append(roll.step().tokens.cpu().numpy())
    return np.concatenate(out)
