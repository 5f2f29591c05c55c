"""Fit the learned reward heads on collected IND training episodes, labelled by the rule reward."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from stages.rl.rewards.heads import EmbeddingHead, ProxyCNN


@dataclass
class FrameSet:
    """Frames 1..T of a set of episodes, with what the heads read and the rule-reward labels."""

    hidden: torch.Tensor  # (M, D) action-WM hidden state, teacher-forced on the real tokens
    done_prob: torch.Tensor  # (M,) action-WM done head
    tokens: torch.Tensor  # (M, h, w)
    reward: torch.Tensor  # (M,) rule reward after the action that led to the frame
    progress: np.ndarray  # (M,) t / T
    episode: np.ndarray  # (M,) index of the episode in the list given


@torch.no_grad()
def teacher_forced(wm, tokens: np.ndarray, actions: np.ndarray, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Hidden states (T, D) and done probs (T,) of real frames 1..T under the true actions.

    tokens (T+1, h, w), actions (T, 7): one episode, stepped through the KV-cached rollout.
    """
    roll = wm.rollout(1)
    roll.reset(torch.as_tensor(np.asarray(tokens[:1], dtype=np.int64), device=device))
    hs, ds = [], []
    for t in range(len(actions)):
        out = roll.step(torch.as_tensor(actions[t : t + 1], device=device),
                        next_tokens=torch.as_tensor(np.asarray(tokens[t + 1 : t + 2], dtype=np.int64), device=device))
        hs.append(out.hidden[0])
        ds.append(out.done_prob[0])
    return torch.stack(hs), torch.stack(ds)


def frame_set(wm, episodes: list, device: str, progress=None) -> FrameSet:
    """episodes: (tokens (T+1, h, w), actions (T, 7), reward (T,)) per episode."""
    hs, ds, toks, rs, prog, epi = [], [], [], [], [], []
    for i, (tokens, actions, reward) in enumerate(episodes):
        h, d = teacher_forced(wm, tokens, actions, device)
        t = len(actions)
        hs.append(h.cpu()), ds.append(d.cpu())
        toks.append(torch.as_tensor(np.asarray(tokens[1:], dtype=np.int64)))
        rs.append(torch.as_tensor(np.asarray(reward, dtype=np.float32)))
        prog.append(np.arange(1, t + 1) / t)
        epi.append(np.full(t, i))
        if progress is not None:
            progress.update(1)
    return FrameSet(torch.cat(hs), torch.cat(ds), torch.cat(toks), torch.cat(rs), np.concatenate(prog), np.concatenate(epi))


def _fit(model, inputs, labels: torch.Tensor, steps: int, lr: float, batch: int, seed: int) -> list[float]:
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    losses = []
    model.train()
    for _ in range(steps):
        idx = torch.randint(0, len(labels), (min(batch, len(labels)),), generator=gen)
        loss = F.mse_loss(model(*[x[idx] for x in inputs]), labels[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    model.eval()
    return losses


def fit_embedding_head(fs: FrameSet, *, steps: int, lr: float, seed: int) -> tuple[EmbeddingHead, list[float]]:
    torch.manual_seed(seed)
    head = EmbeddingHead(fs.hidden.shape[1])
    return head, _fit(head, [fs.hidden], fs.reward, steps, lr, 256, seed)


def fit_proxy(fs: FrameSet, tokenizer, *, steps: int, lr: float, seed: int) -> tuple[ProxyCNN, list[float]]:
    """The proxy CNN reads frames decoded by the tokenizer, as the world model's frames are."""
    torch.manual_seed(seed)
    third, wrist = tokenizer.decode(fs.tokens)
    cnn = ProxyCNN()
    return cnn, _fit(cnn, [third.cpu(), wrist.cpu()], fs.reward, steps, lr, 64, seed)
