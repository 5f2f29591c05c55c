"""scripts/horizon_probe.py: the frame k steps before a demonstration's first success, and its recorded actions from there."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from horizon_probe import start_k_before  # noqa: E402


def test_start_k_before_counts_back_from_the_frame_before_success():
    starts = ["f0", "f1", "f2", "f3"]  # frames 0-3; frame 4 is the first successful one
    assert start_k_before(starts, 1) == "f3"
    assert start_k_before(starts, 4) == "f0"


def test_start_k_before_is_none_when_the_episode_is_shorter_or_k_is_not_positive():
    assert start_k_before(["f0", "f1"], 3) is None
    assert start_k_before(["f0", "f1"], 0) is None
    assert start_k_before([], 1) is None


def test_demo_actions_are_the_recorded_ones_then_the_last_repeated():
    import numpy as np
    from horizon_probe import demo_actions

    actions = np.arange(5 * 7, dtype=np.float32).reshape(5, 7)  # (T', 7)
    np.testing.assert_array_equal(demo_actions(actions, 1, 3), actions[1:4])
    padded = demo_actions(actions, 3, 4)  # two recorded, then the last one twice
    assert padded.shape == (4, 7)
    np.testing.assert_array_equal(padded[:2], actions[3:5])
    np.testing.assert_array_equal(padded[2:], actions[[4, 4]])
