"""evaluate renders as collect did: it reads collect's sim.json and refuses a disagreeing setting."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from stages.collect.dataset import SimFacts, read_sim_facts, write_sim_facts
from stages.evaluate import Config
from stages.evaluate.jobs import sim_settings


def test_evaluate_takes_collects_camera_and_mesh_and_refuses_others(tmp_path):
    write_sim_facts(tmp_path, SimFacts(image_size=96, robot_mesh="stock"))
    ctx = SimpleNamespace(input=lambda name: tmp_path)
    assert sim_settings(ctx, Config()) == (96, "stock")
    assert sim_settings(ctx, Config(image_size=96)) == (96, "stock")
    with pytest.raises(ValueError, match="evaluate.image_size = 64 but collect rendered with image_size = 96"):
        sim_settings(ctx, Config(image_size=64))
    with pytest.raises(ValueError, match="robot_mesh"):
        sim_settings(ctx, Config(robot_mesh="lowpoly"))


def test_a_collect_artifact_without_sim_json_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="rerun collect"):
        read_sim_facts(tmp_path)
