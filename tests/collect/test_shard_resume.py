"""The collect stage resumes at shard level: a shard finished before a kill is put back from its
checkpoint, not collected again; a damaged checkpoint is redone; without a checkpoint dir nothing is saved."""
import json
from pathlib import Path

import pytest

from stages.collect import resume
from stages.collect.resume import checkpoint_name, collect_or_resume


@pytest.fixture
def fake_worker(monkeypatch):
    """collect_shard stand-in: writes the shard and counts its calls."""
    calls = []

    def collect_shard(job):
        assert "checkpoints" not in job  # the worker sees the job it always saw
        calls.append(job["path"])
        Path(job["path"]).write_bytes(b"mcap bytes of " + job["task"].encode())
        return {"task": job["task"], "episodes": [{"episode_id": "e0", "shard": Path(job["path"]).name}],
                "stats": {"written": 1}}

    monkeypatch.setattr("stages.collect.worker.collect_shard", collect_shard)
    return calls


def _job(out: Path, ckpt: Path | None) -> dict:
    return {"path": str(out / "push-0000.mcap"), "task": "push", "checkpoints": None if ckpt is None else str(ckpt)}


def test_a_finished_shard_is_resumed_from_its_checkpoint_not_collected_again(tmp_path, fake_worker):
    ckpt = tmp_path / "partial"
    first, second = tmp_path / "run1", tmp_path / "run2"  # the killed run's staging dir, then the next run's
    first.mkdir(), second.mkdir()
    result = collect_or_resume(_job(first, ckpt))
    assert fake_worker == [str(first / "push-0000.mcap")]
    assert (ckpt / checkpoint_name("push-0000.mcap")).is_dir()
    again = collect_or_resume(_job(second, ckpt))
    assert fake_worker == [str(first / "push-0000.mcap")]  # not called again
    assert again == {**result, "resumed": True} and (second / "push-0000.mcap").read_bytes() == b"mcap bytes of push"
    assert "resumed" not in result


def test_a_damaged_checkpoint_is_redone(tmp_path, fake_worker):
    ckpt, out = tmp_path / "partial", tmp_path / "run"
    out.mkdir()
    collect_or_resume(_job(out, ckpt))
    (ckpt / checkpoint_name("push-0000.mcap") / resume.RESULT).write_text(json.dumps({"task": "pull"}) + "\n")
    (out / "push-0000.mcap").unlink()
    result = collect_or_resume(_job(out, ckpt))
    assert len(fake_worker) == 2 and result["task"] == "push"


def test_without_a_checkpoint_dir_it_collects_and_saves_nothing(tmp_path, fake_worker):
    out = tmp_path / "run"
    out.mkdir()
    collect_or_resume(_job(out, None))
    collect_or_resume(_job(out, None))
    assert len(fake_worker) == 2 and sorted(p.name for p in tmp_path.iterdir()) == ["run"]
