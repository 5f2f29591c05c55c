"""The local executor: every node in a fresh spawned process, several at once for a sweep's independent nodes of one stage."""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Any, Callable, Sequence

from pipeline.execute import execute_node


def _die_with_parent(parent: int) -> None:
    """Pool-worker initializer: the worker ends when the process that started it dies.

    Without it a ``kill -9`` (or Ctrl-C, or SIGTERM) of ``pipeline run`` leaves its workers running
    their stage to the end, holding the key's lock, so the next run waits on them without a word.
    Linux: the kernel sends SIGKILL (prctl PR_SET_PDEATHSIG); elsewhere a thread watches the parent.
    """
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(1, int(signal.SIGKILL)) == 0:  # 1 = PR_SET_PDEATHSIG
            if os.getppid() != parent:  # it died before prctl took effect
                os._exit(1)
            return
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


SHARED_CORES_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}
"""Set in the workers of a pool that runs several at once (unless this process's environment sets the
variable): torch's OpenMP threads then sleep between parallel regions instead of spinning for the
cores the other workers need. Measured (benchmarks/wave_threads.py, PPO in the world-model env, two
rl-like processes of 2 torch threads on a 2-core EPYC, 2026-12-04): 0.44x the env steps/s of running
them one after another when they spin, 1.23x when they sleep; it changes scheduling only, never a
result. A pool of one worker keeps the default (spinning): 0.92x when one process sleeps alone."""


def _worker_init(parent: int, env: dict[str, str]) -> None:
    """Pool-worker initializer: ``env`` into the environment before anything imports torch, then
    ``_die_with_parent``."""
    os.environ.update(env)
    _die_with_parent(parent)


def shared_cores_env(workers: int) -> dict[str, str]:
    """What ``_pool`` adds to its workers' environment: ``SHARED_CORES_ENV`` where ``workers`` > 1,
    less any variable this process already sets (the user's choice wins)."""
    if workers <= 1:
        return {}
    return {k: v for k, v in SHARED_CORES_ENV.items() if k not in os.environ}


def _pool(workers: int, fresh: bool = False) -> ProcessPoolExecutor:
    """Spawn (not fork): simulators and torch threads do not survive a fork reliably. ``fresh``: one
    task per worker process, so no task sees what an earlier one left behind. Several workers share
    the cores, so they get ``SHARED_CORES_ENV``."""
    return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                               initializer=_worker_init, initargs=(os.getpid(), shared_cores_env(workers)),
                               max_tasks_per_child=1 if fresh else None)


def pool_map(fn: Callable[[Any], Any], items: Sequence[Any], jobs: int, desc: str, progress) -> list:
    """``[fn(x) for x in items]`` on ``jobs`` spawned processes, results in order, with a progress bar."""
    out: list[Any] = [None] * len(items)
    with progress(len(items), desc, "it") as bar, _pool(min(jobs, len(items))) as pool:
        futures = {pool.submit(fn, x): i for i, x in enumerate(items)}
        pending = set(futures)
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in finished:
                out[futures[f]] = f.result()
                bar.update(1)
    return out


class LocalExecutor:
    """Runs a wave of ready nodes, each in a process of its own.

    A node never runs in a process that ran another one: caches filled by an earlier stage (a loaded
    tokenizer, a text encoder) skip the random draws of their construction, so the same stage with
    the same seed trained a different policy after another stage than alone (sft's first-epoch loss
    0.8321 after train_wm vs 0.8383 on its own, docs/engine.md).

    Nodes of *one* stage (a sweep's fan-out: twelve ``rl`` points) cost about the same, so they share
    the cores: one node per worker, each told ``jobs = 1``. Nodes of *different* stages do not
    (``sft`` takes two minutes, ``train_wm`` an hour): splitting the cores between them left the long
    one on one core for the whole hour after the short one ended, so they run one after another,
    each with all ``jobs`` cores (for its torch threads and its own ``ctx.map``).
    """

    name = "local"

    def __init__(self, jobs: int):
        self.jobs = jobs

    def run_wave(self, payloads: list[dict], on_done: Callable[[dict, dict | None, BaseException | None], None]) -> None:
        groups: dict[str, list[dict]] = {}
        for p in payloads:
            groups.setdefault(p["stage"], []).append(p)
        for group in groups.values():
            if self.jobs <= 1 or len(group) <= 1:
                for p in group:
                    self._in_processes([p], 1, on_done)
            else:
                for p in group:
                    p["jobs"] = 1  # the workers already use the cores
                self._in_processes(group, min(self.jobs, len(group)), on_done)

    @staticmethod
    def _in_processes(payloads: list[dict], workers: int, on_done) -> None:
        with _pool(workers, fresh=True) as pool:
            futures = {pool.submit(execute_node, p): p for p in payloads}
            for f in futures:
                try:
                    on_done(futures[f], f.result(), None)
                except Exception as e:  # noqa: BLE001 - reported by the runner
                    on_done(futures[f], None, e)

    def close(self) -> None:
        pass
