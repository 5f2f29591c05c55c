"""scripts/horizon_probe.py's choice of start: the frame k steps before a demonstration's first success."""
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
