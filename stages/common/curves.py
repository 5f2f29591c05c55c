"""Training curves as TensorBoard event files inside the artifact being built.

A stage writes them to ``<out>/tensorboard/``: while it runs, ``out`` is its staging directory
(``tensorboard --logdir <store>/tmp`` watches every running stage); once committed, the curves are
part of the artifact (``python -m pipeline show STAGE`` prints the command). The same numbers are in
the stage's ``metrics.json``; these files exist for the field's habit of watching a run live.
"""
from __future__ import annotations

from pathlib import Path

TENSORBOARD_DIR = "tensorboard"


class Curves:
    """``scalar(tag, value, step)`` appends one point; flushed every ``flush_secs`` and at ``close``."""

    def __init__(self, out_dir: str | Path, flush_secs: int = 30):
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(str(Path(out_dir) / TENSORBOARD_DIR), flush_secs=flush_secs)

    def scalar(self, tag: str, value: float, step: int) -> None:
        if value is not None:
            self.writer.add_scalar(tag, float(value), int(step))

    def series(self, tag: str, values: list, start: int = 1) -> None:
        """A whole curve at once (steps ``start``, ``start + 1``, ...)."""
        for i, v in enumerate(values):
            self.scalar(tag, v, start + i)

    def close(self) -> None:
        self.writer.close()

    def __enter__(self) -> "Curves":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
