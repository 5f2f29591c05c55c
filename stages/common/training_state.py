"""A training loop's whole state kept as a stage checkpoint, so a killed run resumes mid-training.

Stages with long optimisation loops (tokenize, train_wm, wm_play's fine-tune) hand their loop a
``save`` function and, when an earlier run of the same key left one, the ``resume`` state it saved
(``pipeline.checkpoints`` keeps it under the key; the engine drops it once the artifact commits).
What goes into the state is the loop's business: everything its remaining steps depend on, RNG
states included, so that a resumed run ends where an uninterrupted one ends.
"""
from __future__ import annotations

from typing import Callable

import torch

# how many times a loop saves its state during training (and once after its last step): every 125 of
# the small tokenizer's 1,500 steps (~6 min on 2 CPU cores), every 250 of train_wm's 3,000 action steps
SAVES_PER_LOOP = 12


def save_every(steps: int) -> int:
    """Steps between two saves of a loop of ``steps`` steps."""
    return max(1, steps // SAVES_PER_LOOP)


def training_checkpoint(checkpoints, name: str) -> tuple[dict | None, Callable[[dict], None]]:
    """(the training state saved under checkpoint ``name`` by an earlier run of this key, or None;
    a function saving a new state there) for a loop's ``resume`` and ``save``."""
    def save(state: dict) -> None:
        with checkpoints.save(name) as d:
            torch.save(state, d / "state.pt")

    found = checkpoints.load(name)
    return (torch.load(found / "state.pt", weights_only=False) if found is not None else None), save
