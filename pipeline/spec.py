"""pydantic models of pipeline.yaml, and loading it with errors that name the key path."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from pipeline.errors import PipelineError
from pipeline.store import RESERVED

SCHEMA = 1


class StageSpec(BaseModel):
    """One node of the DAG: the module that implements it, what it needs, its config section."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    module: str = Field(description="importable module exposing `Config` and `run(ctx)`")
    needs: list[str] = Field(default_factory=list, description="stages whose artifacts this stage reads")
    version: int = Field(1, description="salt: bump to force a rerun without changing code or config")
    config: dict[str, Any] = Field(default_factory=dict, description="values over the stage's Config defaults")


class SweepSpec(BaseModel):
    """An ablation: the cartesian product of `axes` (dotted config paths -> values; 'a.x+b.y' sets both paths to each value)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    axes: dict[str, list[Any]] = Field(description="e.g. {'rl.reward': [wm, rule], 'rl.seed': [0, 1]}")
    until: str | None = Field(None, description="last stage of every point (default: the last stage)")
    report: str | None = Field(None, description="'module:function' called with the points after the table is written")
    description: str = ""

    @field_validator("axes")
    @classmethod
    def _axes_nonempty(cls, axes: dict[str, list[Any]]) -> dict[str, list[Any]]:
        if not axes:
            raise ValueError("a sweep needs at least one axis")
        for path, values in axes.items():
            if any("." not in part for part in path.split("+")):
                raise ValueError(f"axis {path!r} must be a dotted path 'stage.key' (or paths tied with '+')")
            if not values:
                raise ValueError(f"axis {path!r} has no values")
        return axes


class PipelineSpec(BaseModel):
    """The whole pipeline.yaml."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)
    schema_version: int = Field(SCHEMA, alias="schema")
    default_profile: str | None = None
    store: str = Field("artifacts", description="store directory, relative to pipeline.yaml")
    device: str = "cpu"
    jobs: int = Field(1, ge=1, description="workers for independent nodes and for stages' own ctx.map")
    stages: dict[str, StageSpec]
    profiles: dict[str, dict[str, dict[str, Any]]] = Field(default_factory=dict)
    sweeps: dict[str, SweepSpec] = Field(default_factory=dict)


def _format_validation(err: ValidationError, prefix: str) -> str:
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in (prefix, *e["loc"]) if p != "")
        if e["type"] == "extra_forbidden":
            lines.append(f"  {loc}: unknown key")
        else:
            lines.append(f"  {loc}: {e['msg']}")
    return "\n".join(lines)


def allowed_keys(model: type[BaseModel]) -> str:
    """Comma-separated field names (aliases where set) of a pydantic model, for error messages."""
    return ", ".join(f.alias or name for name, f in model.model_fields.items())


def load_spec(path: str | Path) -> PipelineSpec:
    """Parse and validate pipeline.yaml; every error names the file and the key path."""
    path = Path(path)
    if not path.is_file():
        raise PipelineError(f"{path}: no such pipeline file")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise PipelineError(f"{path}: not valid YAML:\n{e}") from None
    if not isinstance(raw, dict):
        raise PipelineError(f"{path}: expected a mapping at the top level, got {type(raw).__name__}")
    try:
        spec = PipelineSpec.model_validate(raw)
    except ValidationError as e:
        msg = _format_validation(e, "")
        hint = ""
        if any(x["type"] == "extra_forbid" or x["type"] == "extra_forbidden" for x in e.errors()):
            hint = f"\n  allowed top-level keys: {allowed_keys(PipelineSpec)}; stage keys: {allowed_keys(StageSpec)}"
        raise PipelineError(f"{path}: invalid pipeline spec:\n{msg}{hint}") from None
    if spec.schema_version != SCHEMA:
        raise PipelineError(f"{path}: schema {spec.schema_version} is not supported (this engine reads schema {SCHEMA})")
    _check_references(spec, path)
    return spec


def _check_references(spec: PipelineSpec, path: Path) -> None:
    names = set(spec.stages)
    clash = sorted(names & set(RESERVED))
    if clash:
        raise PipelineError(f"{path}: stages.{clash[0]}: the name is reserved for the store's own directories "
                            f"({', '.join(RESERVED)}); rename the stage")
    for name, st in spec.stages.items():
        for need in st.needs:
            if need not in names:
                raise PipelineError(f"{path}: stages.{name}.needs: unknown stage {need!r}; known stages: {', '.join(spec.stages)}")
    for prof, overlay in spec.profiles.items():
        for stage in overlay:
            if stage not in names:
                raise PipelineError(f"{path}: profiles.{prof}.{stage}: unknown stage; known stages: {', '.join(spec.stages)}")
    if spec.default_profile is not None and spec.default_profile not in spec.profiles:
        raise PipelineError(f"{path}: default_profile {spec.default_profile!r} is not one of profiles: {', '.join(spec.profiles) or '(none)'}")
    for sw_name, sw in spec.sweeps.items():
        for axis in sw.axes:
            for part in axis.split("+"):
                stage = part.strip().split(".", 1)[0]
                if stage not in names:
                    raise PipelineError(f"{path}: sweeps.{sw_name}.axes.{axis}: unknown stage {stage!r}; known stages: {', '.join(spec.stages)}")
        if sw.until is not None and sw.until not in names:
            raise PipelineError(f"{path}: sweeps.{sw_name}.until: unknown stage {sw.until!r}; known stages: {', '.join(spec.stages)}")
    from pipeline.graph import topo_order  # cycle check names the cycle

    topo_order({n: s.needs for n, s in spec.stages.items()}, source=str(path))
