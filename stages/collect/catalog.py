"""The scene catalog: primitive objects x containers x tables, and its seeded IND/OOD split.

A scene is one object (shape x size x color, named as in instructions: "small red cylinder"), one
container (plate or bowl) and one table. The out-of-domain (OOD) split holds out (paper §8.1):
  - unseen objects: every scene with one of ``ood_objects`` held-out objects, and
  - unseen object-container combinations: ``ood_pairs`` (IND object, container) pairs whose
    scenes are held out although the object and the container each appear in IND scenes.
Tables appear in both splits.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

SHAPES = ("cube", "cylinder", "sphere", "capsule")
CONTAINERS = ("plate", "bowl")


@dataclass(frozen=True)
class ObjectSpec:
    """One primitive object; ``half_size`` is half its largest horizontal extent in metres."""

    name: str  # instruction name, e.g. "small red cylinder"
    shape: str  # one of SHAPES
    half_size: float
    color: tuple[float, float, float]


@dataclass(frozen=True)
class TableSpec:
    name: str
    color: tuple[float, float, float]


@dataclass(frozen=True)
class Scene:
    """A scene from the catalog; ``to_dict`` gives the JSON the envs take as their ``scene`` kwarg."""

    scene_id: str
    object: ObjectSpec
    container: str  # one of CONTAINERS
    table: TableSpec
    split: str  # "ind" | "ood"
    ood_reason: str | None = None  # "unseen_object" | "unseen_combination" for OOD scenes

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "Scene":
        obj = d["object"]
        return Scene(
            scene_id=d["scene_id"],
            object=ObjectSpec(obj["name"], obj["shape"], float(obj["half_size"]), tuple(obj["color"])),
            container=d["container"],
            table=TableSpec(d["table"]["name"], tuple(d["table"]["color"])),
            split=d["split"],
            ood_reason=d.get("ood_reason"),
        )


def _slug(text: str) -> str:
    return text.replace(" ", "-")


def build_objects(shapes, sizes: dict[str, float], colors: dict[str, tuple]) -> list[ObjectSpec]:
    """Every shape x size x color combination, in a fixed order."""
    for s in shapes:
        if s not in SHAPES:
            raise ValueError(f"collect config: unknown shape {s!r} in 'shapes'; expected one of {SHAPES}")
    return [
        ObjectSpec(f"{size} {color} {shape}", shape, float(half), tuple(float(c) for c in rgb))
        for shape in shapes
        for size, half in sizes.items()
        for color, rgb in colors.items()
    ]


def build_catalog(
    shapes, sizes: dict, colors: dict, tables: dict, *, ood_objects: int, ood_pairs: int, split_seed: int
) -> list[Scene]:
    """All scenes (object x container x table) with a seeded IND/OOD split."""
    objects = build_objects(shapes, sizes, colors)
    table_specs = [TableSpec(n, tuple(float(c) for c in rgb)) for n, rgb in tables.items()]
    if len(objects) < ood_objects + 1:
        raise ValueError(f"collect config: ood_objects={ood_objects} leaves no IND object among {len(objects)}")
    rng = np.random.default_rng(split_seed)
    held_out_objects = {objects[i].name for i in rng.choice(len(objects), size=ood_objects, replace=False)}
    ind_objects = [o for o in objects if o.name not in held_out_objects]
    pairs = [(o.name, c) for o in ind_objects for c in CONTAINERS]
    # A held-out pair must leave its object and its container seen in IND: pick at most one
    # container per object, so the object's other container stays IND.
    order = rng.permutation(len(ind_objects))
    if ood_pairs > len(ind_objects):
        raise ValueError(f"collect config: ood_pairs={ood_pairs} exceeds the {len(ind_objects)} IND objects")
    held_out_pairs = {(ind_objects[i].name, CONTAINERS[int(rng.integers(len(CONTAINERS)))]) for i in order[:ood_pairs]}
    assert held_out_pairs <= set(pairs)
    scenes = []
    for obj in objects:
        for container in CONTAINERS:
            for table in table_specs:
                if obj.name in held_out_objects:
                    split, reason = "ood", "unseen_object"
                elif (obj.name, container) in held_out_pairs:
                    split, reason = "ood", "unseen_combination"
                else:
                    split, reason = "ind", None
                sid = f"{_slug(obj.name)}__{container}__{_slug(table.name)}"
                scenes.append(Scene(sid, obj, container, table, split, reason))
    return scenes


def write_scenes_json(scenes: list[Scene], path: Path) -> None:
    """Write the catalog and its split (the artifact's ``scenes.json``)."""
    doc = {
        "n_scenes": len(scenes),
        "n_ind": sum(s.split == "ind" for s in scenes),
        "n_ood": sum(s.split == "ood" for s in scenes),
        "scenes": [s.to_dict() for s in scenes],
    }
    path.write_text(json.dumps(doc, indent=1) + "\n")


def read_scenes_json(path: Path) -> dict[str, Scene]:
    """scene_id -> Scene from an artifact's ``scenes.json``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: is this a collect artifact directory?")
    return {d["scene_id"]: Scene.from_dict(d) for d in json.loads(path.read_text())["scenes"]}
