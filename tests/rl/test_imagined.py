"""Imagined-success precision read off at stricter done-head thresholds (stages.rl.imagined)."""
import numpy as np
import pytest

from stages.rl.imagined import precision_at, precision_metrics, replay_row


def test_a_replay_counts_only_if_it_succeeds_by_the_imagined_done():
    probs = np.array([0.1, 0.6, 0.7, 0.8, 0.85, 0.95, 0.2])  # done head after each policy step
    early = replay_row("push/a", probs, first_success=5, theta=0.5)
    assert (early.done_at, early.success) == (2, False)  # imagined done at step 2, the simulator only at 5
    late = replay_row("push/a", probs, first_success=5, theta=0.9)
    assert (late.done_at, late.success) == (6, True)
    never = replay_row("push/a", probs, first_success=3, theta=0.99)
    assert (never.done_at, never.success) == (-1, True)  # no imagined done: success by the horizon


def test_precision_at_a_stricter_threshold_drops_the_false_alarms():
    rows = [replay_row("pull/a", np.array([0.2, 0.6, 0.55]), -1, 0.5),  # false alarm at 0.6
            replay_row("push/b", np.array([0.3, 0.8, 0.98]), 3, 0.5),  # imagined at 2, real at 3: false at 0.5
            replay_row("push/c", np.array([0.99, 0.99, 0.99]), 1, 0.5)]  # true
    base = precision_metrics(rows)
    assert (base["imagined_done"], base["imagined_and_replayed"]) == (3, 1)
    assert base["precision"] == pytest.approx(1 / 3)
    strict = precision_at(rows, 0.97)
    assert (strict["imagined_done"], strict["imagined_and_replayed"]) == (2, 2)
    assert strict["precision"] == pytest.approx(1.0)
    assert precision_at(rows, 0.5) == base  # the stage's own threshold gives back its rows


def test_tcp_error_averages_only_over_replays_that_lasted():
    from stages.rl.imagined import tcp_error_at

    rows = [replay_row("a", np.zeros(3), -1, 0.5, (0.01, 0.02, 0.03)), replay_row("b", np.zeros(3), 1, 0.5, (0.05,))]
    errs = tcp_error_at(rows, (1, 3, 4))
    assert errs[1] == pytest.approx(0.03)  # both replays reached step 1
    assert errs[3] == pytest.approx(0.03)  # only "a" reached step 3
    assert errs[4] is None  # no replay lasted 4 steps


def test_tcp_gap_is_read_up_to_the_imagined_done_and_split_by_outcome():
    from stages.rl.imagined import tcp_gap_by_outcome, tcp_gap_to_done

    drifted = replay_row("pick/a", np.array([0.1, 0.2, 0.9, 0.9]), -1, 0.5, (0.01, 0.04, 0.02, 0.30))
    assert tcp_gap_to_done(drifted) == pytest.approx(0.04)  # done at step 3: the 0.30 after it does not count
    real = replay_row("push/b", np.array([0.1, 0.9, 0.9, 0.9]), 2, 0.5, (0.005, 0.01))  # replay stopped at success
    assert tcp_gap_to_done(real) == pytest.approx(0.01)
    never = replay_row("pull/c", np.zeros(4), -1, 0.5, (0.5, 0.5, 0.5, 0.5))
    assert tcp_gap_to_done(never) is None  # no imagined done, no gap
    assert tcp_gap_to_done(replay_row("pull/d", np.ones(4), -1, 0.5)) is None  # no TCP record (no proprio head)
    gaps = tcp_gap_by_outcome([drifted, real, never])
    assert gaps["true"] == pytest.approx([0.01]) and gaps["false"] == pytest.approx([0.04])


def test_a_token_matches_only_if_all_its_code_bits_do():
    from stages.rl.imagined import token_match

    a = np.zeros((3, 2, 2), bool)  # 3 code bits on a 2 x 2 grid
    b = a.copy()
    b[0, 0, 0] = True  # one bit of one cell differs
    b[:, 1, 1] = True  # all bits of another
    assert token_match(a, a) == 1.0 and token_match(a, b) == 0.5


def test_token_accuracy_averages_only_over_replays_that_lasted():
    from stages.rl.imagined import token_accuracy_at

    a, b = replay_row("a", np.zeros(3), -1, 0.5), replay_row("b", np.zeros(3), 1, 0.5)
    a.token_accuracy, a.copy_accuracy = (0.9, 0.8, 0.7), (0.95, 0.9, 0.85)
    b.token_accuracy, b.copy_accuracy = (0.5,), (0.7,)
    acc = token_accuracy_at([a, b], (1, 3, 4))
    assert acc[1] == pytest.approx((0.7, 0.825)) and acc[3] == pytest.approx((0.7, 0.85)) and acc[4] is None


def test_a_done_that_must_persist_drops_a_one_step_blip():
    rows = [replay_row("pull/a", np.array([0.2, 0.9, 0.1, 0.1, 0.1]), -1, 0.5),  # one-step blip, never real
            replay_row("push/b", np.array([0.3, 0.8, 0.9, 0.95, 0.9]), 4, 0.5)]  # held from step 2, real at 4
    assert precision_at(rows, 0.5)["imagined_and_replayed"] == 0  # both fire at step 2, neither real by then
    held = precision_at(rows, 0.5, persist=3)
    assert (held["imagined_done"], held["imagined_and_replayed"]) == (1, 1)  # b's run of 3 ends at step 4


def test_the_guard_vetoes_an_imagined_success_it_does_not_confirm():
    from stages.rl.imagined import guarded_row, precision_head_only

    head = np.array([0.2, 0.9, 0.95, 0.95])
    rows = [guarded_row("pull/a", head, np.array([0.1, 0.2, 0.3, 0.2]), -1, 0.5),  # the guard never confirms
            guarded_row("push/b", head, np.array([0.1, 0.3, 0.8, 0.9]), 3, 0.5)]  # confirmed at 3, real at 3
    assert [r.done_at for r in rows] == [-1, 3]
    guarded = precision_metrics(rows)
    assert (guarded["imagined_done"], guarded["imagined_and_replayed"], guarded["precision"]) == (1, 1, 1.0)
    alone = precision_head_only(rows, 0.5)  # the done head alone fires at step 2 in both, neither real by then
    assert (alone["imagined_done"], alone["imagined_and_replayed"], alone["precision"]) == (2, 0, 0.0)
    with pytest.raises(ValueError, match="head_probs"):
        precision_head_only([replay_row("a", head, -1, 0.5)], 0.5)
    # a success held for 2 steps: the head and the guard together reach theta at 3 and 4 in b only
    held = guarded_row("push/b", head, np.array([0.1, 0.3, 0.8, 0.9]), 3, 0.5, persist=2)
    assert held.done_at == 4 and held.success and held.head_probs == rows[1].head_probs
    assert precision_head_only([held], 0.5, persist=2)["imagined_done"] == 1  # the head alone holds from step 2: done at 3
