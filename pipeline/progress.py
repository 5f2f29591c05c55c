"""Progress for stages: a tqdm bar on a terminal, a plain line every ~30 s in a log or pipe.

Off a terminal a heartbeat thread prints the current line when no update has printed one for an
interval, so a log shows a line at least every ~30 s even while one item takes minutes.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from typing import Callable, TextIO

from tqdm import tqdm

LINE_INTERVAL_S = 30.0


class Progress:
    """A context manager with ``update(n)`` and ``postfix(**kv)``, in one of three modes.

    ``bar``: tqdm on stderr (stderr is a terminal, or ``PIPELINE_PROGRESS=1``, or ``enabled=True``).
    ``lines``: stderr is not a terminal (a log file, ``nohup``, a batch job): one plain line at most
    every ``interval`` seconds, ``desc done/total (pct), rate, ETA, postfix``, and a last one at
    close if any was printed. A heartbeat thread prints the line (with how long ago the last item
    finished) whenever an interval passes without one, so slow items never leave the log silent.
    ``off``: ``enabled=False`` or ``PIPELINE_PROGRESS=0``. Every mode counts, so a stage can log its
    rate at the end.

    :param total: items expected, or None when unknown (no percentage, no ETA)
    :param desc: what is counted, e.g. ``"train_wm: action steps"``
    :param unit: the item's name in the rate (``"it"`` -> ``it/s``)
    :param enabled: force the bar (True) or silence (False); None picks by terminal and environment
    :param interval: seconds between plain lines
    :param clock: monotonic seconds (tests pass a fake one)
    :param stream: where plain lines go (default: stderr at the time of printing)
    :param heartbeat: run the heartbeat thread in ``lines`` mode (tests with a fake clock call
        :meth:`beat` themselves)
    """

    def __init__(self, total: int | None, desc: str, unit: str = "it", enabled: bool | None = None, *,
                 interval: float = LINE_INTERVAL_S, clock: Callable[[], float] = time.monotonic,
                 stream: TextIO | None = None, heartbeat: bool = True):
        env = os.environ.get("PIPELINE_PROGRESS")
        if enabled is False or (enabled is None and env == "0"):
            self.mode = "off"
        elif enabled or env == "1" or sys.stderr.isatty():
            self.mode = "bar"
        else:
            self.mode = "lines"
        self.total, self.desc, self.unit, self.n = total, desc, unit, 0
        self._skipped = 0  # items done by an earlier run (resumed): counted in n, not in the rate
        self._clock, self._interval, self._stream = clock, interval, stream
        self._t0 = self._last_line = self._last_item = clock()
        self._lines = 0
        self._postfix: dict = {}
        self._bar = tqdm(total=total, desc=desc, unit=unit, leave=False, dynamic_ncols=True) if self.mode == "bar" else None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = None
        if self.mode == "lines" and heartbeat:
            self._thread = threading.Thread(target=self._heartbeat, name=f"progress: {desc}", daemon=True)
            self._thread.start()

    def update(self, n: int = 1) -> None:
        with self._lock:
            self.n += n
            self._last_item = self._clock()
            if self._bar is not None:
                self._bar.update(n)
            elif self.mode == "lines" and self._last_item - self._last_line >= self._interval:
                self._print_line()

    def resumed(self, n: int) -> None:
        """Count ``n`` items an earlier, interrupted run already did: they advance ``n`` (and the
        bar) but not the rate, so the ETA after a resume reflects this run's own speed."""
        with self._lock:
            self.n += n
            self._skipped += n
            if self._bar is not None:
                self._bar.update(n)

    def beat(self) -> bool:
        """Print the line if an interval passed since the last one (the heartbeat); True if printed."""
        with self._lock:
            now = self._clock()
            if self.mode != "lines" or now - self._last_line < self._interval:
                return False
            self._print_line(idle=now - self._last_item)
            return True

    def _heartbeat(self) -> None:
        while True:
            with self._lock:
                wait = self._interval - (self._clock() - self._last_line)
            if self._stop.wait(max(wait, 0.01)):
                return
            self.beat()

    def postfix(self, **kv) -> None:
        self._postfix = kv
        if self._bar is not None:
            self._bar.set_postfix(kv, refresh=False)

    @property
    def rate(self) -> float:
        """Items per second since the bar was created (items counted by :meth:`resumed` left out)."""
        return (self.n - self._skipped) / max(self._clock() - self._t0, 1e-9)

    def line(self, idle: float | None = None) -> str:
        """``desc done/total (pct), rate unit/s, ETA h:mm:ss, postfix`` as of now.

        :param idle: seconds since the last item finished; from one interval on the line says so
        """
        rate = self.rate
        parts = [f"{self.desc} {self.n}/{self.total} ({100 * self.n / self.total:.0f}%)" if self.total
                 else f"{self.desc} {self.n}"]
        parts.append(f"{rate:.3g} {self.unit}/s" if rate >= 1 or rate == 0 else f"{1 / rate:.3g} s/{self.unit}")
        if self.total and rate > 0:
            parts.append(f"ETA {_hms((self.total - self.n) / rate)}" if self.n < self.total else f"done in {_hms(self._clock() - self._t0)}")
        if self._postfix:
            parts.append(" ".join(f"{k}={v}" for k, v in self._postfix.items()))
        if idle is not None and idle >= self._interval:
            parts.append(f"working, last {self.unit} {_hms(idle)} ago" if self.n else f"working on the first {self.unit}")
        return ", ".join(parts)

    def _print_line(self, idle: float | None = None) -> None:
        print(f"  {self.line(idle)}", file=self._stream or sys.stderr, flush=True)
        self._last_line = self._clock()
        self._lines += 1

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        with self._lock:
            if self._bar is not None:
                self._bar.close()
                self._bar = None
            elif self.mode == "lines" and self._lines:
                self._print_line()
            self.mode = "off"  # closed: a second close prints nothing, the heartbeat stops

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _hms(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"
