"""What a successful step is paid when success ends an episode (the payout every environment applies)."""
from __future__ import annotations

import numpy as np


def success_return(max_step_reward: float, steps_left, gamma: float):
    """The reward of a step that ends its episode in success: ``max_step_reward`` for that step and
    for each of the ``steps_left`` steps it would have had until truncation, discounted by ``gamma``
    (the value of an absorbing state that keeps paying the most any step can). Scalar or array."""
    k = np.maximum(np.asarray(steps_left, dtype=np.float64), 0.0) + 1.0  # this step and the ones left
    total = k if gamma == 1.0 else (1.0 - gamma**k) / (1.0 - gamma)
    return max_step_reward * total
