"""Progress bars for stages (tqdm on stderr), disabled when not attached to a terminal unless forced."""
from __future__ import annotations

import os
import sys
import time

from tqdm import tqdm


class Progress:
    """A thin tqdm wrapper: a context manager with ``update(n)`` and ``postfix(**kv)``.

    When disabled it still counts, so a stage can log its rate at the end.
    """

    def __init__(self, total: int | None, desc: str, unit: str = "it", enabled: bool | None = None):
        if enabled is None:
            enabled = sys.stderr.isatty() or os.environ.get("PIPELINE_PROGRESS") == "1"
        self.total, self.desc, self.n = total, desc, 0
        self._t0 = time.perf_counter()
        self._bar = tqdm(total=total, desc=desc, unit=unit, leave=False, dynamic_ncols=True) if enabled else None

    def update(self, n: int = 1) -> None:
        self.n += n
        if self._bar is not None:
            self._bar.update(n)

    def postfix(self, **kv) -> None:
        if self._bar is not None:
            self._bar.set_postfix(kv, refresh=False)

    @property
    def rate(self) -> float:
        """Items per second since the bar was created."""
        return self.n / max(time.perf_counter() - self._t0, 1e-9)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
