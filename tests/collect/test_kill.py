"""Killing a collection worker mid-shard (SIGKILL) leaves no partial episode visible, and the next run of
the key resumes: the shards finished before the kill come back from their checkpoints, byte for byte."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from stages.collect.dataset import SHARD_DIR, Dataset

pytestmark = pytest.mark.sim
REPO = Path(__file__).resolve().parents[2]

SCRIPT = """
import sys, torch
torch.set_num_threads(1)
from pathlib import Path
from pipeline.context import StageContext
from stages.collect import Config, run
cfg = Config(tasks=("push", "pull"), ind_scenes=1, ood_scenes=0, optimal_per_scene=3, suboptimal_ratio=0,
             replay_fraction=0, episodes_per_shard=2)
run(StageContext(stage="collect", config=cfg, inputs={}, out=Path(sys.argv[1]), seed=0, partial=Path(sys.argv[2])))
"""


def test_sigkill_mid_shard_leaves_only_whole_episodes(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    partial = tmp_path / "partial"  # the key's checkpoint dir, kept across the kill
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, str(out), str(partial)], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    shards = out / SHARD_DIR
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None:
            finished, writing = list(shards.glob("*.mcap")), list(shards.glob("*.mcap.tmp"))
            if finished and writing:
                break  # a later shard is being written right now: kill at once (a shard takes seconds)
            time.sleep(0.05)
        assert proc.poll() is None, "collection finished before it could be killed"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert list(shards.glob("*.mcap.tmp")), "expected the killed shard's unfinished temp file"
    assert not (out / "episodes.jsonl").exists()
    ds = Dataset(out)  # rebuilt from finished shards only
    assert len(ds.episodes) >= 2
    assert {m.shard for m in ds.episodes} == {p.name for p in shards.glob("*.mcap")}
    for m in ds.episodes:
        ep = ds.load(m.episode_id)
        assert len(ep.action) == m.length and len(ep.third) == m.length + 1
        assert ep.success[-1] and np.isfinite(ep.action).all()
    # the next run of the key, in a fresh staging dir, resumes: finished shards are not collected again
    finished = {p.name: p.read_bytes() for p in shards.glob("*.mcap")}
    again = tmp_path / "again"
    again.mkdir()
    subprocess.run([sys.executable, "-c", SCRIPT, str(again), str(partial)], cwd=REPO, env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
    resumed, metrics = Dataset(again), json.loads((again / "metrics.json").read_text())
    assert len(resumed.episodes) == metrics["episodes"] > len(ds.episodes)  # finished what the kill cut short
    assert metrics["shards_resumed"] == len(finished)
    assert {m.episode_id for m in ds.episodes} <= {m.episode_id for m in resumed.episodes}
    for name, data in finished.items():  # the same file, linked back from its checkpoint, not a re-collection
        assert (again / SHARD_DIR / name).read_bytes() == data
        assert (again / SHARD_DIR / name).stat().st_ino == (shards / name).stat().st_ino
