"""stages.sft.dagger's bookkeeping: a round's demonstrations survive the checkpoint, seeds stay apart."""
from __future__ import annotations

import numpy as np

from stages.sft.dagger import DAGGER_SEED, Rollout, load_round, round_seeds, save_round, summary
from stages.sft.data import Demo


def test_a_rounds_demonstrations_and_rows_come_back_from_its_checkpoint(tmp_path):
    rng = np.random.default_rng(0)
    demos = [Demo(f"dagger/push/s{i}/{i}", "push it", rng.integers(0, 255, (n + 1, 16, 8)), rng.normal(size=(n + 1, 10)),
                  rng.normal(size=(n, 7)).astype(np.float32), rng.normal(size=(n + 1, 3)),
                  None if i == 0 else rng.integers(0, 255, (16, 8))) for i, n in enumerate((3, 5))]
    rows = [Rollout("push/s0", 6_000_000, 4, False, True, "success", 120, 3),
            Rollout("pull/s1", 6_000_001, 75, False, False, "no_plan"), Rollout("pull/s1", 6_000_002, 9, True, False, "none")]
    save_round(tmp_path, demos, rows)
    back, back_rows = load_round(tmp_path)
    assert back_rows == rows
    for a, b in zip(demos, back):
        assert (a.episode_id, a.instruction) == (b.episode_id, b.instruction)
        for field in ("tokens", "proprio", "actions", "obj_xyz"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        np.testing.assert_array_equal(b.first, a.tokens[0] if a.first is None else a.first)
    counts = summary(rows)
    assert counts == {"starts": 3, "policy_success": 1, "rested": 1, "takeover_success": 1, "takeover_failed": 0,
                      "takeover_no_plan": 1, "pairs": 3}


def test_round_seeds_differ_between_rounds_and_sft_seeds_and_lie_above_every_other_stream():
    a, b, c = round_seeds(0, 0, 300), round_seeds(0, 1, 300), round_seeds(1, 0, 300)
    assert not (set(a) & set(b)) and not (set(a) & set(c)) and min(a + b + c) >= DAGGER_SEED
