"""The DAG: topological order, cycles, and stage selection (--until / --only / --from)."""
from __future__ import annotations

from typing import Iterable, Mapping, Sequence

from pipeline.errors import PipelineError


def topo_order(needs: Mapping[str, Sequence[str]], source: str = "pipeline") -> list[str]:
    """Stages in dependency order (ties keep declaration order); a cycle raises naming it."""
    order: list[str] = []
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done

    def visit(n: str, path: list[str]) -> None:
        if state.get(n) == 2:
            return
        if state.get(n) == 1:
            cycle = path[path.index(n):] + [n]
            raise PipelineError(f"{source}: cycle in needs: {' needs '.join(cycle)}")
        state[n] = 1
        for m in needs[n]:
            visit(m, path + [n])
        state[n] = 2
        order.append(n)

    for n in needs:
        visit(n, [])
    return order


def ancestors(needs: Mapping[str, Sequence[str]], stage: str) -> set[str]:
    """Every stage ``stage`` transitively needs (not including itself)."""
    out: set[str] = set()
    stack = list(needs[stage])
    while stack:
        n = stack.pop()
        if n not in out:
            out.add(n)
            stack.extend(needs[n])
    return out


def descendants(needs: Mapping[str, Sequence[str]], stage: str) -> set[str]:
    """Every stage that transitively needs ``stage`` (not including itself)."""
    return {n for n in needs if stage in ancestors(needs, n)}


def check_stage(needs: Mapping[str, Sequence[str]], stage: str, flag: str) -> str:
    if stage not in needs:
        raise PipelineError(f"{flag}: unknown stage {stage!r}; known stages: {', '.join(topo_order(needs))}")
    return stage


def select(
    needs: Mapping[str, Sequence[str]],
    until: str | None = None,
    only: Iterable[str] = (),
    start: str | None = None,
) -> list[str]:
    """The stages a run may execute, in order.

    ``until``: the stage and its ancestors. ``only``: exactly these stages (their inputs must be
    cached). ``start`` (--from): the stage and its descendants (ancestors must be cached).
    Combined flags intersect.
    """
    order = topo_order(needs)
    chosen = set(order)
    if until is not None:
        check_stage(needs, until, "--until")
        chosen &= ancestors(needs, until) | {until}
    only = list(only)
    if only:
        for s in only:
            check_stage(needs, s, "--only")
        chosen &= set(only)
    if start is not None:
        check_stage(needs, start, "--from")
        chosen &= descendants(needs, start) | {start}
    return [s for s in order if s in chosen]
