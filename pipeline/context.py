"""The stage contract: what a stage's ``run(ctx)`` receives from the engine.

A stage package ``stages/<name>/`` exposes ``Config`` (a pydantic model, ``extra="forbid"``,
frozen) and ``run(ctx: StageContext) -> None``. It reads its inputs from ``ctx.inputs`` (read-only,
committed artifacts of the stages it ``needs``), writes every output under ``ctx.out`` (a fresh
staging directory), and never reads another stage's config. When ``run`` returns, the engine
commits ``ctx.out`` atomically; when it raises, the staging directory is discarded. A stage may also
expose ``unread_needs(config) -> list[str]``, those of its ``needs`` a config does not read
(``pipeline.plan.Project.used_needs``); ``ctx.inputs`` then holds the rest. A long stage may keep
named checkpoints with ``ctx.checkpoints()`` that outlive a killed run of the same key
(``pipeline.checkpoints``).
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from pydantic import BaseModel

from pipeline.checkpoints import Checkpoints
from pipeline.progress import Progress


@dataclass(frozen=True)
class StageContext:
    """Everything a stage may use. Built by the runner; stages never construct it in production."""

    stage: str  # the stage's name in pipeline.yaml
    config: BaseModel  # the stage's own validated config section
    inputs: Mapping[str, Path]  # needed stage name -> its committed artifact directory (read-only)
    out: Path  # fresh staging directory; everything the stage produces goes here
    seed: int  # ``config.seed`` when the config has one, else 0; the engine has already seeded
    # ``random``, ``numpy`` and (if the stage module imported it) ``torch`` with it
    device: str = "cpu"  # torch device string; never part of a key
    jobs: int = 1  # how many workers ``map`` may use
    profile: str = "default"
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("stage"))
    mapper: Callable[..., list] | None = None  # set by the executor; see ``map``
    progress_factory: Callable[..., Progress] | None = None
    partial: Path | None = None  # this key's checkpoint directory (kept across a kill); None: checkpoints off

    def checkpoints(self) -> Checkpoints:
        """Named checkpoints that survive a crash or kill of this key, so a rerun resumes (pipeline.checkpoints)."""
        return Checkpoints(self.partial, self.log)

    def progress(self, total: int | None, desc: str, unit: str = "it") -> Progress:
        """A progress bar for long work inside the stage; use as a context manager, call ``update(n)``."""
        if self.progress_factory is None:
            return Progress(total=total, desc=desc, unit=unit, enabled=False)
        return self.progress_factory(total=total, desc=desc, unit=unit)

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any] | Iterable[Any], desc: str = "") -> list:
        """``[fn(x) for x in items]`` fanned out on the active executor (processes or Ray tasks).

        ``fn`` must be a module-level function and items/results picklable. Results keep order.
        """
        items = list(items)
        if self.mapper is None or self.jobs <= 1 or len(items) <= 1:
            out = []
            with self.progress(len(items), desc or fn.__name__) as bar:
                for x in items:
                    out.append(fn(x))
                    bar.update(1)
            return out
        return self.mapper(fn, items, jobs=self.jobs, desc=desc or fn.__name__, progress=self.progress)

    def input(self, name: str) -> Path:
        """The artifact directory of the needed stage ``name``, with a clear error if it is not an input."""
        try:
            return self.inputs[name]
        except KeyError:
            raise KeyError(f"stage {self.stage!r} has no input {name!r}; its inputs are {sorted(self.inputs)}") from None

    def write_metrics(self, metrics: Mapping[str, Any]) -> Path:
        """Write ``metrics.json`` into the staging dir (sweeps build their results table from it)."""
        path = self.out / "metrics.json"
        path.write_text(json.dumps(_finite(dict(metrics)), indent=2, sort_keys=True, default=float, allow_nan=False) + "\n")
        return path


def _finite(x: Any) -> Any:
    """NaN / inf become None (null), so metrics.json is strict JSON."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if hasattr(x, "item") and getattr(x, "ndim", 1) == 0:  # numpy / torch scalars
        return _finite(x.item())
    return x
