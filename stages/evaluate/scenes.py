"""Evaluation scenes: the collect catalog's IND / OOD scenes, plus extra scenes from config or a YAML file.

An extra scene is plain data, e.g. (YAML)::

    - {shape: cylinder, size: large, color: [0.9, 0.5, 0.1], color_name: orange, container: bowl, table: dark grey}

``size`` is a size name of the collect catalog (``small``, ``large``) or a half extent in metres;
``table`` a table name of the catalog or an RGB triple. Extra scenes are evaluated as their own
split, ``extra``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field

class ExtraScene(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    shape: Literal["cube", "cylinder", "sphere", "capsule"]
    size: float | str = Field("small", description="a catalog size name or a half extent in metres")
    color: tuple[float, float, float] = Field(description="RGB in [0, 1]")
    color_name: str = Field(description="the word the instruction uses, e.g. 'orange'")
    container: Literal["plate", "bowl"] = "plate"
    table: str | tuple[float, float, float] = "wood"


def load_extra_scenes(value) -> list:
    """A list of scene dicts, or a path to a YAML file holding one (content is what enters the key)."""
    if isinstance(value, (str, Path)):
        path = Path(value)
        if not path.is_file():
            raise ValueError(f"extra_scenes: no such YAML file {path}")
        try:
            value = yaml.safe_load(path.read_text()) or []
        except yaml.YAMLError as e:
            raise ValueError(f"extra_scenes: {path} is not valid YAML: {e}") from None
        if not isinstance(value, list):
            raise ValueError(f"extra_scenes: {path} must hold a list of scenes, got {type(value).__name__}")
    return value


def to_scene(extra: ExtraScene, index: int, tables: dict, sizes: dict[str, float]) -> dict:
    """The collect catalog's scene dict for an extra scene; ``sizes``/``tables`` come from the catalog."""
    from stages.collect.catalog import ObjectSpec, Scene, TableSpec

    if isinstance(extra.size, str):
        if extra.size not in sizes:
            raise ValueError(f"extra scene {index}: unknown size {extra.size!r}; catalog sizes: {sorted(sizes)} or metres")
        half, size_name = sizes[extra.size], extra.size
    else:
        half = float(extra.size)
        size_name = min(sizes, key=lambda k: abs(sizes[k] - half))  # the nearest catalog word for the instruction
    if isinstance(extra.table, str):
        if extra.table not in tables:
            raise ValueError(f"extra scene {index}: unknown table {extra.table!r}; catalog tables: {sorted(tables)}")
        table = TableSpec(extra.table, tuple(tables[extra.table]))
    else:
        table = TableSpec(f"table{index}", tuple(extra.table))
    name = f"{size_name} {extra.color_name} {extra.shape}"
    obj = ObjectSpec(name, extra.shape, half, tuple(extra.color))
    return Scene(f"extra{index:02d}-{extra.color_name}-{extra.shape}-{extra.container}", obj, extra.container, table,
                 "extra", "user_added").to_dict()
