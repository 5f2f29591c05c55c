"""Executors run independent nodes and stages' ``ctx.map`` work: ``local`` (default) or ``ray``."""
from __future__ import annotations

from typing import Callable

from pipeline.errors import PipelineError

EXECUTORS = ("local", "ray")


def get_executor(name: str, jobs: int):
    """The executor called ``name`` (``local`` or ``ray``), ready to run waves of nodes."""
    if name == "local":
        from pipeline.executors.local import LocalExecutor

        return LocalExecutor(jobs)
    if name == "ray":
        from pipeline.executors.ray_executor import RayExecutor

        return RayExecutor(jobs)
    raise PipelineError(f"--executor {name!r}: unknown executor; known: {', '.join(EXECUTORS)}")


def mapper_for(name: str) -> Callable[..., list]:
    """The ``ctx.map`` implementation of executor ``name`` (process pool or Ray tasks)."""
    if name == "ray":
        from pipeline.executors.ray_executor import ray_map

        return ray_map
    from pipeline.executors.local import pool_map

    return pool_map
