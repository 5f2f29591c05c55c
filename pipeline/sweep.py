"""Sweeps: expand axes into points, plan them together, and tabulate each point's metrics."""
from __future__ import annotations

import csv
import importlib
import io
import itertools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import blake3

from pipeline.errors import PipelineError
from pipeline.plan import Node, Project, assign, deep_merge, flatten, parse_set
from pipeline.store import write_json_atomic


@dataclass
class Point:
    values: dict[str, Any]  # axis path -> value
    overrides: dict[str, dict[str, Any]]
    label: str
    nodes: list[Node]

    @property
    def last(self) -> Node:
        return self.nodes[-1]


def axis_paths(axis: str) -> list[str]:
    """The config paths an axis sets: ``'sft.seed+rl.seed'`` ties two paths to one value per point."""
    return [p.strip() for p in axis.split("+")]


def _resolve_axis(name: str, given: str, axes: list[str]) -> str:
    """The sweep axis that ``--axis given=...`` means: its exact name, or the one tied axis naming that path."""
    if given in axes:
        return given
    hits = [a for a in axes if given in axis_paths(a)]
    if len(hits) != 1:
        raise PipelineError(f"--axis {given!r}: not an axis of sweep {name!r}; its axes: {', '.join(axes)}")
    return hits[0]


def parse_axes(items: list[str]) -> dict[str, list]:
    """``--axis PATH=[v1, v2]`` strings -> {path: values}; values are a non-empty YAML list."""
    import yaml

    out = {}
    for item in items:
        path, eq, raw = item.partition("=")
        try:
            vals = yaml.safe_load(raw) if eq else None
        except yaml.YAMLError as e:
            raise PipelineError(f"--axis {item!r}: value is not valid YAML ({e})") from None
        if not path or not isinstance(vals, list) or not vals:
            raise PipelineError(f"--axis {item!r}: expected stage.key=[value, ...] with at least one value")
        out[path] = vals
    return out


def expand(project: Project, name: str, profile: str | None, sets: dict, until: str | None,
           axis_values: dict[str, list] | None = None) -> tuple[list[Point], str]:
    """Every point of sweep ``name`` as planned nodes, and the sweep's last stage.

    ``axis_values`` replaces the values of some of the sweep's axes (``--axis rl.seed=[0,1]``; a path
    of a tied axis such as ``sft.seed+rl.seed`` names that whole axis).
    """
    if name not in project.spec.sweeps:
        raise PipelineError(f"sweep {name!r}: unknown sweep; known: {', '.join(project.spec.sweeps) or '(none)'}")
    sw = project.spec.sweeps[name]
    last = until or sw.until or project.order[-1]
    if last not in project.needs:
        raise PipelineError(f"--until: unknown stage {last!r}; known stages: {', '.join(project.order)}")
    given = {_resolve_axis(name, k, list(sw.axes)): v for k, v in (axis_values or {}).items()}
    axes = [(path, given.get(path, vals)) for path, vals in sw.axes.items()]
    axis_overrides = parse_set([f"{p}=x" for path, _ in axes for p in axis_paths(path)])  # shape only, validated below
    project.check_overrides(axis_overrides, f"sweeps.{name}.axes")
    points = []
    for combo in itertools.product(*(vals for _, vals in axes)):
        values = {path: v for (path, _), v in zip(axes, combo)}
        over: dict[str, dict[str, Any]] = {}
        for axis, v in values.items():
            for path in axis_paths(axis):
                stage, *rest = path.split(".")
                assign(over.setdefault(stage, {}), rest, v)
        merged = deep_merge(sets, over)
        label = f"sweep:{name}:" + ",".join(f"{k}={v}" for k, v in values.items())
        nodes = project.plan([last], profile, merged, label)
        points.append(Point(values, merged, label, nodes))
    return points, last


def results_table(project: Project, name: str, points: list[Point]) -> Path:
    """Write results.{json,csv,md} for the sweep from each point's last-stage metrics.json."""
    rows = []
    for pt in points:
        node = pt.last
        mpath = project.store.path(node.stage, node.key) / "metrics.json"
        try:
            metrics = flatten(json.loads(mpath.read_text()), scalars_only=True)
        except (OSError, ValueError):
            metrics = {}
        rows.append({**{k: v for k, v in pt.values.items()}, **metrics, "key": node.short})
    cols: list[str] = []
    for r in rows:
        cols.extend(c for c in r if c not in cols)
    digest = blake3.blake3("".join(pt.last.key for pt in points).encode()).hexdigest()[:12]
    out = project.store.root / "sweeps" / name / digest
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "results.json", {"sweep": name, "columns": cols, "rows": rows})
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols)
    w.writeheader()
    w.writerows(rows)
    (out / "results.csv").write_text(buf.getvalue())
    (out / "results.md").write_text(markdown_table(cols, rows))
    return out


def run_report(project: Project, name: str, points: list[Point], out: Path) -> Path | None:
    """Call the sweep's ``report`` hook (``'module:function'``) with every point's values and artifacts."""
    hook = project.spec.sweeps[name].report
    if hook is None:
        return None
    mod_name, _, fn_name = hook.partition(":")
    try:
        fn = getattr(importlib.import_module(mod_name), fn_name)
    except (ImportError, AttributeError) as e:
        raise PipelineError(f"sweeps.{name}.report: cannot load {hook!r} ({e})") from None
    pts = [{"values": pt.values, "label": pt.label,
            "artifacts": {n.stage: project.store.path(n.stage, n.key) for n in pt.nodes}} for pt in points]
    return fn(points=pts, out=out)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def markdown_table(cols: list[str], rows: list[dict]) -> str:
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |")
    return "\n".join(lines) + "\n"
