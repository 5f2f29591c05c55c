"""When a policy "came to rest": it commanded (almost) no arm motion for several policy steps running.

The evaluate stage reports it per episode (docs/evaluate.md), and the sft stage's DAgger rounds hand
an episode to the planner there (``stages.sft.dagger``); one definition for both.
"""
from __future__ import annotations

import numpy as np

REST_ACTION = 0.03  # |commanded TCP displacement| (env action units, dims 0-2) below which a policy step is "at rest"
REST_STEPS = 3  # an episode "came to rest" when its policy commanded rest this many steps running (docs/evaluate.md)


def longest_rest(position_commands: np.ndarray) -> int:
    """The longest run of consecutive policy steps whose commanded TCP displacement (steps, 3) is below
    ``REST_ACTION``: how long the policy stopped acting. 0 for an episode with no step."""
    best = run = 0
    for still in np.linalg.norm(np.asarray(position_commands, dtype=np.float64).reshape(-1, 3), axis=1) < REST_ACTION:
        run = run + 1 if still else 0
        best = max(best, run)
    return best
