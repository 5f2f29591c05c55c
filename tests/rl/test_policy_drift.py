"""scripts/policy_drift.py's measure: no drift for the same actions; flips and changes counted as defined."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from policy_drift import drift  # noqa: E402


def test_the_same_actions_do_not_drift_and_a_change_is_measured_as_defined():
    rng = np.random.default_rng(0)
    demo = rng.normal(size=(200, 7)).astype(np.float32)
    sft = demo + 0.1 * rng.normal(size=demo.shape).astype(np.float32)
    same = drift(sft, sft.copy(), demo)
    assert same["flip"] == 0 and same["arm"] == 0 and same["r2_sft"] == same["r2_ppo"] > 0.9
    ppo = sft.copy()
    ppo[:50, 6] *= -1  # a quarter of the gripper decisions flipped
    ppo[:, :3] *= 1.5  # every translation half as long again
    d = drift(sft, ppo, demo)
    assert d["flip"] == 0.25 and abs(d["arm"] - 0.5) < 1e-6 and d["r2_ppo"] < d["r2_sft"]
