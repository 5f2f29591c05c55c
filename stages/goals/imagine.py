"""Imagined goal frames (paper Eq. 6): the text world model rolls out from an environment's
initial frame, conditioned on its instruction, until its done head passes theta."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Imagined:
    tokens: np.ndarray  # (E, h, w) the chosen goal frame of each environment
    done_prob: np.ndarray  # (E,) done probability of that frame
    steps: np.ndarray  # (E,) imagined steps until it (1-based)
    reached: np.ndarray  # (E,) bool: done passed theta within the step cap


@torch.no_grad()
def imagine_goals(wm, start_tokens: torch.Tensor, instructions: list[str], *, theta: float, max_steps: int,
                  candidates: int, seed: int, progress=None) -> Imagined:
    """Roll out ``candidates`` imagined futures per environment and keep the most confident goal.

    start_tokens (E, h, w). Each candidate stops at its first frame with done >= theta; a candidate
    that never gets there keeps its most-done frame. Per environment, the chosen candidate is the
    one with the highest done probability at its stopping frame (reached ones first).
    """
    e, h, w = start_tokens.shape
    b = e * candidates
    emb = wm.text_embedding(instructions)  # (E, 384)
    roll = wm.rollout(b, seed=seed)
    roll.reset(start_tokens.repeat_interleave(candidates, 0), emb.repeat_interleave(candidates, 0))
    best_tok = start_tokens.cpu().repeat_interleave(candidates, 0)  # (B, h, w), on the CPU like the rest of the bookkeeping
    best_p = torch.full((b,), -1.0)
    best_step = torch.zeros(b, dtype=torch.long)
    stopped = torch.zeros(b, dtype=torch.bool)
    for t in range(1, max_steps + 1):
        out = roll.step()
        p = out.done_prob.cpu()
        better = ~stopped & (p > best_p)
        best_tok[better] = out.tokens.cpu()[better]
        best_p[better], best_step[better] = p[better], t
        stopped |= p >= theta
        if progress is not None:
            progress.update(1)
        if bool(stopped.all()):
            break
    score = best_p + stopped.float()  # reached candidates rank above all unreached ones
    pick = score.view(e, candidates).argmax(1) + torch.arange(e) * candidates  # (E,)
    return Imagined(best_tok[pick].numpy(), best_p[pick].numpy(), best_step[pick].numpy(), stopped[pick].numpy())
