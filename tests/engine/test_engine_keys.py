"""Stage keys follow the science, not the engine: editing ``pipeline/`` changes no stage's code digest."""
from __future__ import annotations

import shutil

import yaml

from pipeline.keys import code_digest, source_closure
from tests.engine.conftest import REPO


def _stage_modules() -> dict[str, str]:
    spec = yaml.safe_load((REPO / "pipeline.yaml").read_text())
    return {name: st["module"] for name, st in spec["stages"].items()}


def _copy_project(tmp_path):
    for d in ("pipeline", "stages"):
        shutil.copytree(REPO / d, tmp_path / d, ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path


def test_no_stage_digest_includes_an_engine_file(tmp_path):
    root = _copy_project(tmp_path)
    for stage, module in _stage_modules().items():
        files = source_closure(module, [root])
        assert files, stage
        assert not [f for f in files if f.is_relative_to(root / "pipeline")], stage


def test_editing_every_engine_module_leaves_every_stage_digest_unchanged(tmp_path):
    root = _copy_project(tmp_path)
    modules = _stage_modules()
    before = {s: code_digest(m, [root]) for s, m in modules.items()}
    engine_files = sorted((root / "pipeline").rglob("*.py"))
    assert len(engine_files) >= 10
    for f in engine_files:
        f.write_text(f.read_text() + "\n# an engine edit\n")
    assert {s: code_digest(m, [root]) for s, m in modules.items()} == before
    # the same edit to a shared science helper does change the digests of the stages that import it
    helper = root / "stages" / "common" / "frame_skip.py"
    helper.write_text(helper.read_text() + "\n# a science edit\n")
    after = {s: code_digest(m, [root]) for s, m in modules.items()}
    assert after["train_wm"] != before["train_wm"] and after["collect"] == before["collect"]
