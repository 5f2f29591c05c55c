"""The Ray executor (optional extra ``pip install .[ray]``): the same ``execute_node`` as Ray tasks.

The store must be on a filesystem every Ray worker sees (a shared mount on a cluster).
"""
from __future__ import annotations

from typing import Any, Callable, Sequence

from pipeline.errors import PipelineError
from pipeline.execute import execute_node


def _ray():
    try:
        import ray
    except ImportError:
        raise PipelineError("--executor ray needs the optional extra: pip install 'ray[default]==2.60.0'") from None
    return ray


def _ensure_init(jobs: int):
    ray = _ray()
    if not ray.is_initialized():
        ray.init(num_cpus=max(jobs, 1), include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    return ray


def ray_map(fn: Callable[[Any], Any], items: Sequence[Any], jobs: int, desc: str, progress) -> list:
    """``ctx.map`` on Ray tasks; results in order."""
    ray = _ensure_init(jobs)
    remote = ray.remote(fn)
    refs = [remote.remote(x) for x in items]
    out = []
    with progress(len(refs), desc, "it") as bar:
        for r in refs:
            out.append(ray.get(r))
            bar.update(1)
    return out


class RayExecutor:
    """Every node of a wave becomes a Ray task running ``execute_node``."""

    name = "ray"

    def __init__(self, jobs: int):
        self.jobs = jobs
        self.ray = _ensure_init(jobs)
        self._remote = self.ray.remote(execute_node)

    def run_wave(self, payloads: list[dict], on_done: Callable[[dict, dict | None, BaseException | None], None]) -> None:
        refs = [(p, self._remote.remote(p)) for p in payloads]
        for p, ref in refs:
            try:
                on_done(p, self.ray.get(ref), None)
            except Exception as e:  # noqa: BLE001
                cause = getattr(e, "cause", None) or e
                on_done(p, None, cause)

    def close(self) -> None:
        pass
