"""Episodes as token sequences for world-model training: load once, sample fixed-length clips.

Episodes are subsampled to one frame every ``frame_skip`` control steps, actions composed
(``stages.common.frame_skip``); everything below counts world-model steps.

Done labels: ``done[t] = success[t]``, the simulator's success flag at observed (kept) frame t (1
from the first frame where the task is achieved on, for as long as it stays achieved). The done
head is trained on frames 1..T of each clip (the frames the model predicts).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch


@dataclass
class Episode:
    episode_id: str
    instruction: str
    split: str  # "ind" | "ood"
    tokens: np.ndarray  # (T+1, N) int64
    actions: np.ndarray  # (T, 7) float32
    done: np.ndarray  # (T+1,) float32 in {0, 1}
    proprio: np.ndarray  # (T+1, 10) float32 robot proprioception (stages.common.proprio)
    kind: str = "optimal"  # collect's trajectory kind (stages.collect.plans.KINDS)

    @property
    def length(self) -> int:
        return len(self.actions)


def load_episodes(collect_dir: Path, tokenize_dir: Path, progress=None, frame_skip: int = 1) -> list[Episode]:
    """Every collected episode with its precomputed tokens, composed actions, done labels and
    proprioception (states read without decoding any image)."""
    from stages.collect.dataset import Dataset
    from stages.common.frame_skip import compose_actions, frame_indices
    from stages.common.proprio import proprio_from_state
    from stages.tokenize.store import TokenStore

    ds, store = Dataset(collect_dir), TokenStore(tokenize_dir)
    out = []
    for meta in ds.episodes:
        if meta.episode_id not in store:
            raise KeyError(f"episode {meta.episode_id!r} of {collect_dir} has no tokens in {tokenize_dir}")
        ep = ds.load_states(meta.episode_id)
        tokens = np.asarray(store.episode(meta.episode_id), dtype=np.int64)
        tokens = tokens.reshape(len(tokens), -1)
        actions = np.asarray(ep["action"], dtype=np.float32)
        if len(tokens) != len(actions) + 1:
            raise ValueError(f"episode {meta.episode_id!r}: {len(tokens)} token frames for {len(actions)} actions "
                             f"(expected T+1 frames for T actions)")
        keep = frame_indices(len(actions), frame_skip)
        out.append(Episode(meta.episode_id, meta.instruction, meta.split, tokens[keep],
                           compose_actions(actions, frame_skip), np.asarray(ep["success"], dtype=np.float32)[keep],
                           proprio_from_state(ep["ee_pose"][keep], ep["qpos"][keep]), meta.kind))
        if progress is not None:
            progress.update(1)
    return out


def split_episodes(episodes: list[Episode], heldout_ids: set[str] | None, holdout_fraction: float,
                   seed: int) -> tuple[list[Episode], list[Episode], list[Episode]]:
    """(train IND, held-out IND, OOD). Uses the tokenizer's held-out IND list when given."""
    ind = [e for e in episodes if e.split == "ind"]
    ood = [e for e in episodes if e.split == "ood"]
    if heldout_ids:
        held = [e for e in ind if e.episode_id in heldout_ids]
    else:
        order = np.random.default_rng(seed).permutation(len(ind))
        n = max(1, int(round(holdout_fraction * len(ind)))) if len(ind) > 1 else 0
        held = [ind[i] for i in order[:n]]
    held_ids = {e.episode_id for e in held}
    train = [e for e in ind if e.episode_id not in held_ids]
    if not train:
        raise ValueError(f"no IND training episodes left ({len(ind)} IND episodes, {len(held)} held out)")
    return train, held, ood


class ClipSampler:
    """Random clips of ``window`` actions (window+1 frames); shorter episodes are padded and masked."""

    def __init__(self, episodes: list[Episode], window: int, text_emb: dict[str, np.ndarray], seed: int):
        self.eps, self.window, self.text = episodes, window, text_emb
        self.rng = np.random.default_rng(seed)
        lengths = np.array([max(e.length - window + 1, 1) for e in episodes], dtype=np.float64)
        self.p = lengths / lengths.sum()  # every clip start equally likely

    def sample(self, batch: int, device) -> dict[str, torch.Tensor]:
        """tokens (B, W+1, N), actions (B, W, 7), text (B, 384), done (B, W), valid (B, W) for frames 1..W."""
        w = self.window
        n = self.eps[0].tokens.shape[1]
        tokens = np.zeros((batch, w + 1, n), np.int64)
        actions = np.zeros((batch, w, 7), np.float32)
        done = np.zeros((batch, w), np.float32)
        valid = np.zeros((batch, w), np.float32)
        text = np.zeros((batch, 384), np.float32)
        for b, i in enumerate(self.rng.choice(len(self.eps), size=batch, p=self.p)):
            ep = self.eps[i]
            start = int(self.rng.integers(0, max(ep.length - w, 0) + 1))
            k = min(w, ep.length - start)  # actions in this clip
            tokens[b, : k + 1] = ep.tokens[start : start + k + 1]
            tokens[b, k + 1 :] = ep.tokens[start + k]
            actions[b, :k] = ep.actions[start : start + k]
            done[b, :k] = ep.done[start + 1 : start + k + 1]
            valid[b, :k] = 1.0
            text[b] = self.text[ep.instruction]
        t = lambda a: torch.from_numpy(a).to(device)  # noqa: E731
        return {"tokens": t(tokens), "actions": t(actions), "text": t(text), "done": t(done), "valid": t(valid)}


def random_mask(shape: tuple[int, int, int], gen: torch.Generator, device) -> torch.Tensor:
    """MaskGIT training mask (B, T, N) bool: per frame a cosine-schedule fraction of tokens, at least one."""
    b, t, n = shape
    r = torch.rand(b, t, 1, generator=gen).to(device)
    count = torch.clamp(torch.floor(n * torch.cos(math.pi / 2 * r)), min=1)  # (B, T, 1)
    ranks = torch.rand(b, t, n, generator=gen).to(device).argsort(-1).argsort(-1)
    return ranks < count


def corrupt_context(tokens: torch.Tensor, max_rate: float, vocab: int, gen: torch.Generator) -> torch.Tensor:
    """Context frames with random token noise, for robustness to the model's own rollout errors.

    tokens (B, T, N) clean context frames -> (B, T, N): each clip draws a rate uniformly in
    [0, ``max_rate``] and replaces that fraction of its tokens (independently per token) by uniform
    random ones. ``max_rate`` 0 returns ``tokens`` itself.
    """
    if max_rate <= 0:
        return tokens
    b = tokens.shape[0]
    rate = torch.rand(b, 1, 1, generator=gen).to(tokens.device) * max_rate  # (B, 1, 1)
    flip = torch.rand(tokens.shape, generator=gen).to(tokens.device) < rate  # (B, T, N)
    noise = torch.randint(0, vocab, tokens.shape, generator=gen).to(tokens.device)  # (B, T, N)
    return torch.where(flip, noise, tokens)


def mix_context(context: torch.Tensor, predicted: torch.Tensor, rate: float, gen: torch.Generator) -> torch.Tensor:
    """Scheduled sampling: context frames replaced, each with probability ``rate``, by the model's own predictions.

    context (B, T, N) frames 0..T-1 the backbone reads; predicted (B, T, N) the model's one-step
    predictions of frames 1..T. Frame 0 is the observed start (a rollout's too) and stays; frame
    j >= 1 becomes ``predicted[:, j - 1]`` (made from the real frames before it) with probability
    ``rate``, drawn per clip and frame. ``rate`` 0 returns ``context`` itself.
    """
    if rate <= 0:
        return context
    b, t, _ = context.shape
    pick = torch.rand(b, t, 1, generator=gen).to(context.device) < rate  # (B, T, 1)
    pick[:, 0] = False
    shifted = torch.cat([context[:, :1], predicted[:, :-1]], 1)  # (B, T, N): prediction of frame j at j
    return torch.where(pick, shifted, context)
