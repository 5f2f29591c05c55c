"""The 'came to rest' measure of the evaluate stage: the longest run of steps a policy commanded
(almost) no TCP displacement, and its per-policy, per-split, per-outcome tally in the report."""
from __future__ import annotations

import numpy as np

from stages.evaluate.episodes import REST_ACTION, REST_STEPS, longest_rest
from stages.evaluate.writeup import came_to_rest, rest_section


def test_the_longest_run_of_resting_steps_is_counted():
    still, move = [0.0, 0.0, REST_ACTION * 0.9], [REST_ACTION * 1.1, 0.0, 0.0]
    assert longest_rest(np.array([still, move, still, still, still, move, still])) == 3
    assert longest_rest(np.array([move, move])) == 0
    assert longest_rest(np.zeros((0, 3))) == 0  # an episode that succeeded at its reset
    # the norm over the three position dims decides, not any one dim
    spread = [REST_ACTION * 0.7] * 3  # each dim below, the norm (1.21 x) above
    assert longest_rest(np.array([spread] * 5)) == 0


def test_episodes_are_tallied_per_policy_split_and_outcome_and_reported():
    rows = [{"policy": "sft", "split": "ind", "success": False, "rest_steps": REST_STEPS},
            {"policy": "sft", "split": "ind", "success": False, "rest_steps": REST_STEPS - 1},
            {"policy": "sft", "split": "ind", "success": True, "rest_steps": 0},
            {"policy": "ppo", "split": "ood", "success": False, "rest_steps": 40},
            {"policy": "ppo", "split": "ood", "success": True}]  # a row from before the measure: left out
    got = came_to_rest(rows)
    assert got == {("sft", "ind", "failed"): (1, 2), ("sft", "ind", "succeeded"): (0, 1), ("ppo", "ood", "failed"): (1, 1)}
    md, page = rest_section(got, {"sft": "Supervised finetune (SFT)"})
    assert "| Supervised finetune (SFT) | IND | 0.50 [" in md and "(1/2) | 0.00 [" in md
    ppo = next(line for line in md.splitlines() if line.startswith("| ppo | OOD | 1.00 ["))
    assert ppo.endswith("(1/1) | - |")  # no successful ppo episode with the measure
    assert "<table" in page
