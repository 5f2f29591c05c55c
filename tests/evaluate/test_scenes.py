"""Extra evaluation scenes: built from the catalog's sizes/tables, loaded from YAML by content."""
import pytest

from stages.evaluate import Config
from stages.evaluate.scenes import ExtraScene, to_scene

SIZES, TABLES = {"small": 0.022, "large": 0.03}, {"wood": (0.55, 0.4, 0.25)}


def test_extra_scene_uses_the_catalogs_sizes_and_tables():
    s = to_scene(ExtraScene(shape="cylinder", size="large", color=(0.9, 0.5, 0.1), color_name="orange", container="bowl"),
                 0, TABLES, SIZES)
    assert s["object"]["half_size"] == 0.03 and s["object"]["name"] == "large orange cylinder"
    assert s["table"]["color"] == (0.55, 0.4, 0.25) and s["split"] == "extra" and s["container"] == "bowl"
    with pytest.raises(ValueError, match="unknown size 'huge'"):
        to_scene(ExtraScene(shape="cube", size="huge", color=(1, 0, 0), color_name="red"), 1, TABLES, SIZES)
    with pytest.raises(ValueError, match="unknown table 'marble'"):
        to_scene(ExtraScene(shape="cube", color=(1, 0, 0), color_name="red", table="marble"), 2, TABLES, SIZES)


def test_yaml_file_content_enters_the_config(tmp_path):
    f = tmp_path / "scenes.yaml"
    f.write_text("- {shape: sphere, size: 0.02, color: [0.6, 0.2, 0.8], color_name: purple}\n")
    cfg = Config(extra_scenes=str(f))
    assert cfg.model_dump(mode="json")["extra_scenes"][0]["color_name"] == "purple"  # content, not the path
    with pytest.raises(ValueError, match="no such YAML file"):
        Config(extra_scenes=str(tmp_path / "missing.yaml"))
