"""Frame skip: kept frames, composed actions, per-step values (no simulator; the sim check is in
tests/collect/test_sim.py::test_composed_actions_repeated_reproduce_success)."""
import numpy as np
import pytest

from stages.common.frame_skip import compose_actions, frame_indices, per_step


def test_kept_frames_start_at_zero_and_end_at_the_last_frame():
    assert frame_indices(8, 4).tolist() == [0, 4, 8]
    assert frame_indices(9, 4).tolist() == [0, 4, 8, 9]
    assert frame_indices(3, 1).tolist() == [0, 1, 2, 3]
    assert frame_indices(2, 5).tolist() == [0, 2]
    with pytest.raises(ValueError, match="frame_skip"):
        frame_indices(5, 0)


def test_repeating_a_composed_action_k_times_gives_the_block_total():
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (10, 7)).astype(np.float32)
    k = 4
    comp = compose_actions(actions, k)
    assert comp.shape == (3, 7)  # blocks [0:4], [4:8], [8:10]
    for j, (a, b) in enumerate([(0, 4), (4, 8), (8, 10)]):
        np.testing.assert_allclose(k * comp[j, :6], actions[a:b, :6].sum(0), rtol=1e-5, atol=1e-6)
        assert comp[j, 6] == actions[b - 1, 6]  # gripper: the block's last target
    np.testing.assert_array_equal(compose_actions(actions, 1), actions)


def test_per_step_values_are_those_after_each_block():
    r = np.arange(10, dtype=np.float32)  # value after action i
    assert per_step(r, 10, 4).tolist() == [3.0, 7.0, 9.0]
    with pytest.raises(ValueError, match="per-action"):
        per_step(r, 11, 4)
    with pytest.raises(ValueError, match=r"\(T, 7\)"):
        compose_actions(np.zeros((5, 6)), 2)
