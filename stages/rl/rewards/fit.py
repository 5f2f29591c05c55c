"""Fit the learned reward heads on collected IND training episodes, labelled by the rule reward."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from stages.rl.rewards.base import StepBatch
from stages.rl.rewards.heads import EmbeddingHead, ProxyCNN


@dataclass
class FrameSet:
    """Frames 1..T of a set of episodes, with what the heads read and the rule-reward labels."""

    hidden: torch.Tensor  # (M, D) action-WM hidden state, teacher-forced on the real tokens
    done_prob: torch.Tensor  # (M,) action-WM done head
    tokens: torch.Tensor  # (M, h, w)
    first_tokens: torch.Tensor  # (E, h, w) each episode's initial frame
    reward: torch.Tensor  # (M,) rule reward after the action that led to the frame
    success: torch.Tensor  # (M,) bool, the simulator's success flag at the frame
    progress: np.ndarray  # (M,) t / T
    episode: np.ndarray  # (M,) index of the episode in the list given

    def episode_batches(self, e: int, decoded: tuple, first_decoded: tuple, goal_rows: np.ndarray) -> tuple[StepBatch, StepBatch]:
        """(initial frame, frames 1..T) of episode ``e`` as reward-module batches.

        decoded: (third, wrist) (M, 3, H, W) of ``tokens``; first_decoded: the same of ``first_tokens``
        (E, ...); goal_rows (M,) each frame's goal row.
        """
        m = np.nonzero(self.episode == e)[0]
        first = StepBatch(self.first_tokens[e: e + 1], torch.zeros(1), torch.zeros(1, self.hidden.shape[1]),
                          goal_rows[m[:1]], first_decoded[0][e: e + 1], first_decoded[1][e: e + 1])
        frames = StepBatch(self.tokens[m], self.done_prob[m], self.hidden[m], goal_rows[m], decoded[0][m],
                           decoded[1][m], rule_reward=self.reward[m].numpy().astype(np.float64))
        return first, frames


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
    """episodes: (tokens (T+1, h, w), actions (T, 7), reward (T,), success (T,)) per episode."""
    hs, ds, toks, firsts, rs, ss, prog, epi = [], [], [], [], [], [], [], []
    for i, (tokens, actions, reward, success) in enumerate(episodes):
        h, d = teacher_forced(wm, tokens, actions, device)
        t = len(actions)
        hs.append(h.cpu()), ds.append(d.cpu())
        toks.append(torch.as_tensor(np.asarray(tokens[1:], dtype=np.int64)))
        firsts.append(torch.as_tensor(np.asarray(tokens[:1], dtype=np.int64)))
        rs.append(torch.as_tensor(np.asarray(reward, dtype=np.float32)))
        ss.append(torch.as_tensor(np.asarray(success, dtype=bool)))
        prog.append(np.arange(1, t + 1) / t)
        epi.append(np.full(t, i))
        if progress is not None:
            progress.update(1)
    return FrameSet(torch.cat(hs), torch.cat(ds), torch.cat(toks), torch.cat(firsts), torch.cat(rs), torch.cat(ss),
                    np.concatenate(prog), np.concatenate(epi))


def _fit(model, inputs, labels: torch.Tensor, steps: int, lr: float, batch: int, seed: int, device: str) -> list[float]:
    """MSE regression of ``model(*inputs)`` on ``labels``, on ``device`` (the model stays there)."""
    model.to(device)
    inputs, labels = [x.to(device) for x in inputs], labels.to(device)
    gen = torch.Generator().manual_seed(seed)  # batches drawn on the CPU: the same on every device
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


def fit_embedding_head(fs: FrameSet, tokenizer, *, steps: int, lr: float, seed: int,
                       device: str = "cpu") -> tuple[EmbeddingHead, list[float]]:
    """The head reads the world model's hidden states (``tokenizer`` unused: same signature as ``fit_proxy``)."""
    torch.manual_seed(seed)
    head = EmbeddingHead(fs.hidden.shape[1])
    return head, _fit(head, [fs.hidden], fs.reward, steps, lr, 256, seed, device)


def fit_proxy(fs: FrameSet, tokenizer, *, steps: int, lr: float, seed: int,
              device: str = "cpu") -> tuple[ProxyCNN, list[float]]:
    """The proxy CNN reads frames decoded by the tokenizer, as the world model's frames are."""
    torch.manual_seed(seed)
    third, wrist = tokenizer.decode(fs.tokens)
    cnn = ProxyCNN()
    return cnn, _fit(cnn, [third, wrist], fs.reward, steps, lr, 64, seed, device)
