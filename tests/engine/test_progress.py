"""Progress off a terminal: a plain line at most every interval, with count, rate and ETA."""
from __future__ import annotations

import io
import sys
import time

from pipeline.progress import Progress


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _progress(monkeypatch, total=400, **kw):
    monkeypatch.delenv("PIPELINE_PROGRESS", raising=False)
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # not a terminal, even under `pytest -s`
    clock, out = FakeClock(), io.StringIO()
    return Progress(total, "train_wm: steps", clock=clock, stream=out, **kw), clock, out


def test_off_a_terminal_a_line_at_most_every_interval(monkeypatch):
    bar, clock, out = _progress(monkeypatch)
    assert bar.mode == "lines"
    for _ in range(100):  # 100 steps in 29 s: no line yet
        clock.t += 0.29
        bar.update(1)
    assert out.getvalue() == ""
    clock.t += 1.0  # 30 s since the start
    bar.update(20)
    assert out.getvalue() == "  train_wm: steps 120/400 (30%), 4 it/s, ETA 0:01:10\n"
    clock.t += 10.0
    bar.update(40)
    assert out.getvalue().count("\n") == 1  # 10 s later: still one line
    bar.postfix(loss="0.123")
    clock.t += 20.0
    bar.update(40)
    last = out.getvalue().splitlines()[-1]
    assert last.startswith("  train_wm: steps 200/400 (50%)") and last.endswith("loss=0.123")
    bar.update(200)
    bar.close()
    assert out.getvalue().splitlines()[-1].startswith("  train_wm: steps 400/400 (100%), 6.67 it/s, done in 0:01:00")
    bar.close()
    assert out.getvalue().count("\n") == 3


def test_a_short_job_prints_nothing(monkeypatch):
    with _progress(monkeypatch)[0] as bar:
        bar.update(400)
    assert bar._stream.getvalue() == ""


def test_unknown_total_and_slow_items(monkeypatch):
    bar, clock, out = _progress(monkeypatch, total=None)
    clock.t += 90.0
    bar.update(2)
    assert out.getvalue() == "  train_wm: steps 2, 45 s/it\n"


def test_silenced_by_environment_or_flag(monkeypatch):
    bar, clock, out = _progress(monkeypatch, enabled=False)
    clock.t += 60.0
    bar.update(5)
    bar.close()
    assert bar.mode == "off" and out.getvalue() == "" and bar.n == 5
    monkeypatch.setenv("PIPELINE_PROGRESS", "0")
    assert Progress(10, "x").mode == "off"
    monkeypatch.setenv("PIPELINE_PROGRESS", "1")
    with Progress(10, "x") as forced:
        assert forced.mode == "bar"


def test_the_heartbeat_prints_while_one_item_takes_long(monkeypatch):
    bar, clock, out = _progress(monkeypatch, total=10, heartbeat=False)
    clock.t += 29.0
    assert not bar.beat() and out.getvalue() == ""  # under an interval: quiet
    clock.t += 6.0  # 35 s and not one item finished
    assert bar.beat()
    assert out.getvalue() == "  train_wm: steps 0/10 (0%), 0 it/s, working on the first it\n"
    assert not bar.beat()  # the heartbeat restarted the interval
    bar.update(1)
    clock.t += 40.0
    assert bar.beat()
    assert out.getvalue().splitlines()[-1] == "  train_wm: steps 1/10 (10%), 75 s/it, ETA 0:11:15, working, last it 0:00:40 ago"
    bar.close()
    assert not bar.beat()  # closed: silent


def test_the_heartbeat_thread_keeps_a_log_alive_and_stops_at_close(monkeypatch):
    monkeypatch.delenv("PIPELINE_PROGRESS", raising=False)
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    out = io.StringIO()
    with Progress(3, "evaluate: episodes", stream=out, interval=0.05) as bar:
        time.sleep(0.5)  # one slow item, no update at all
        assert bar._thread.is_alive()
        beats = out.getvalue().count("\n")
        assert 3 <= beats <= 11, out.getvalue()
        assert "working on the first it" in out.getvalue()
    assert not bar._thread.is_alive()
    after = out.getvalue()
    time.sleep(0.2)
    assert out.getvalue() == after  # nothing printed once closed


def test_resumed_items_count_but_not_in_the_rate(monkeypatch):
    """A run resumed at 300/400 that then does 10 items in 30 s: 3 s/it, so the 90 left take 4.5
    min, not the ~9 s that counting the resumed 300 in the rate would promise."""
    bar, clock, out = _progress(monkeypatch, heartbeat=False)
    bar.resumed(300)
    assert bar.n == 300 and bar.rate == 0
    clock.t += 30.0
    bar.update(10)
    assert out.getvalue() == "  train_wm: steps 310/400 (78%), 3 s/it, ETA 0:04:30\n"
