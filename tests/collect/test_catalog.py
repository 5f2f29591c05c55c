"""The scene catalog and its IND/OOD split (no simulator)."""
import pytest

from stages.collect import Config, scene_catalog
from stages.collect.catalog import CONTAINERS, build_catalog, read_scenes_json, write_scenes_json


def test_catalog_has_enough_named_primitive_objects():
    scenes = scene_catalog(Config())
    objects = {s.object.name: s.object for s in scenes}
    assert len(objects) >= 20
    assert {s.container for s in scenes} == set(CONTAINERS)
    assert len({s.table.name for s in scenes}) == 2
    assert all(len(name.split()) == 3 for name in objects)  # "<size> <color> <shape>"
    assert len({s.scene_id for s in scenes}) == len(scenes)


def test_split_is_disjoint_and_as_defined():
    scenes = scene_catalog(Config())
    ind = [s for s in scenes if s.split == "ind"]
    ood = [s for s in scenes if s.split == "ood"]
    assert not {s.scene_id for s in ind} & {s.scene_id for s in ood}
    assert 0.15 <= len(ood) / len(scenes) <= 0.25  # about 80/20
    ind_objects = {s.object.name for s in ind}
    ind_pairs = {(s.object.name, s.container) for s in ind}
    unseen_obj = [s for s in ood if s.ood_reason == "unseen_object"]
    unseen_combo = [s for s in ood if s.ood_reason == "unseen_combination"]
    assert unseen_obj and unseen_combo
    assert all(s.object.name not in ind_objects for s in unseen_obj)
    for s in unseen_combo:  # object and container each seen in IND, but never together
        assert s.object.name in ind_objects
        assert (s.object.name, s.container) not in ind_pairs
        assert any(i.container == s.container for i in ind)


def test_split_is_seeded():
    c = Config()
    a = build_catalog(c.shapes, c.sizes, c.colors, c.tables, ood_objects=4, ood_pairs=6, split_seed=0)
    b = build_catalog(c.shapes, c.sizes, c.colors, c.tables, ood_objects=4, ood_pairs=6, split_seed=0)
    d = build_catalog(c.shapes, c.sizes, c.colors, c.tables, ood_objects=4, ood_pairs=6, split_seed=1)
    assert [s.split for s in a] == [s.split for s in b]
    assert [s.split for s in a] != [s.split for s in d]


def test_scenes_json_round_trip(tmp_path):
    scenes = scene_catalog(Config())
    write_scenes_json(scenes, tmp_path / "scenes.json")
    back = read_scenes_json(tmp_path / "scenes.json")
    assert [back[s.scene_id] for s in scenes] == scenes


def test_bad_catalog_config_errors():
    c = Config()
    with pytest.raises(ValueError, match="unknown shape"):
        build_catalog(("pyramid",), c.sizes, c.colors, c.tables, ood_objects=1, ood_pairs=0, split_seed=0)
    with pytest.raises(Exception, match="extra"):
        Config(nonsense=1)
