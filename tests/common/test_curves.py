"""Training curves land in <out>/tensorboard as event files TensorBoard reads back."""
from stages.common.curves import TENSORBOARD_DIR, Curves


def test_curves_are_readable_tensorboard_scalars(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    with Curves(tmp_path) as c:
        c.series("sft/loss_train", [1.0, 0.5, 0.25])
        c.scalar("ppo/approx_kl", 0.01, 64)
        c.scalar("ppo/approx_kl", None, 128)  # a missing statistic is skipped
    acc = EventAccumulator(str(tmp_path / TENSORBOARD_DIR))
    acc.Reload()
    assert [(e.step, e.value) for e in acc.Scalars("sft/loss_train")] == [(1, 1.0), (2, 0.5), (3, 0.25)]
    assert [e.step for e in acc.Scalars("ppo/approx_kl")] == [64]
