"""MCAP shards: written == read, only finished shards are visible (no simulator)."""
import json

import numpy as np
import pytest
from mcap.reader import make_reader

from stages.collect.dataset import SHARD_DIR, Dataset, EpisodeMeta, write_index
from stages.collect.mcap_io import ShardWriter


def _episode(rng, T, size=16):
    return dict(
        third=rng.integers(0, 256, (T + 1, size, size, 3), dtype=np.uint8),
        wrist=rng.integers(0, 256, (T + 1, size, size, 3), dtype=np.uint8),
        action=rng.uniform(-1, 1, (T, 7)).astype(np.float32),
        ee_pose=rng.normal(size=(T + 1, 7)).astype(np.float32),
        qpos=rng.normal(size=(T + 1, 9)).astype(np.float32),
        reward=rng.uniform(0, 1, T).astype(np.float32),
        success=rng.random(T + 1) < 0.5,
    )


def _meta(eid, split="ind"):
    return dict(episode_id=eid, task="push", instruction="push the small red cube forward", scene_id="s", object="small red cube",
                container="bowl", table="wood", split=split, kind="optimal", seed=3, success=True)


def _write_shard(root, name, episodes, finish=True):
    w = ShardWriter(root / SHARD_DIR / name)
    metas = []
    for eid, arrays, split in episodes:
        meta = {**_meta(eid, split), "length": len(arrays["action"])}
        start, end = w.write_episode(meta, arrays)
        metas.append(EpisodeMeta.from_dict({**meta, "shard": name, "start_ns": start, "end_ns": end}))
    if finish:
        w.close()
    return metas, w


@pytest.fixture
def artifact(tmp_path):
    (tmp_path / SHARD_DIR).mkdir()
    rng = np.random.default_rng(0)
    eps = [("a", _episode(rng, 5), "ind"), ("b", _episode(rng, 9), "ood"), ("c", _episode(rng, 1), "ind")]
    metas, _ = _write_shard(tmp_path, "push-0000.mcap", eps[:2])
    metas2, _ = _write_shard(tmp_path, "push-0001.mcap", eps[2:])
    write_index(tmp_path, metas + metas2)
    return tmp_path, {e[0]: e[1] for e in eps}


def test_round_trip_is_exact(artifact):
    root, written = artifact
    ds = Dataset(root)
    assert [m.episode_id for m in ds.episodes] == ["a", "b", "c"]
    for eid, arrays in written.items():
        ep = ds.load(eid)
        for k, v in arrays.items():
            got = getattr(ep, k)
            assert got.dtype == v.dtype and got.shape == v.shape, k
            assert np.array_equal(got, v), k
        assert ep.meta.length == len(arrays["action"])


def test_iter_frames_streams_every_frame_of_the_split(artifact):
    root, written = artifact
    ds = Dataset(root)
    seen = list(ds.iter_frames("wrist", split="ind"))
    assert [(e, t) for e, t, _ in seen] == [("a", t) for t in range(6)] + [("c", 0), ("c", 1)]
    for eid, t, frame in seen:
        assert np.array_equal(frame, written[eid]["wrist"][t])
    assert len(list(ds.iter_frames("third"))) == 6 + 10 + 2
    with pytest.raises(ValueError, match="view"):
        next(ds.iter_frames("top"))


def test_index_can_be_rebuilt_from_shard_summaries(artifact):
    root, written = artifact
    (root / "episodes.jsonl").unlink()
    ds = Dataset(root)
    assert sorted(m.episode_id for m in ds.episodes) == ["a", "b", "c"]
    assert np.array_equal(ds.load("b").third, written["b"]["third"])


def test_unfinished_shard_is_invisible(tmp_path):
    (tmp_path / SHARD_DIR).mkdir()
    rng = np.random.default_rng(1)
    _write_shard(tmp_path, "pull-0000.mcap", [("done", _episode(rng, 3), "ind")])
    _, w = _write_shard(tmp_path, "pull-0001.mcap", [("half", _episode(rng, 3), "ind")], finish=False)
    assert w.tmp.exists()
    assert [m.episode_id for m in Dataset(tmp_path).episodes] == ["done"]
    w.abort()
    assert not w.tmp.exists()


def test_shard_is_standard_mcap_with_compressed_images(artifact):
    root, _ = artifact
    with open(root / SHARD_DIR / "push-0000.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {s.name for s in summary.schemas.values()}
        assert {"foxglove.CompressedImage", "roboscape.Step", "roboscape.Episode"} <= schemas
        _, channel, msg = next(reader.iter_messages(topics=["/third/image"]))
        img = json.loads(msg.data)
        assert img["format"] == "png" and img["frame_id"] == "third" and channel.message_encoding == "json"


def test_episode_with_wrong_lengths_is_rejected(tmp_path):
    (tmp_path / SHARD_DIR).mkdir()
    arrays = _episode(np.random.default_rng(2), 4)
    arrays["qpos"] = arrays["qpos"][:-1]
    w = ShardWriter(tmp_path / SHARD_DIR / "x-0000.mcap")
    with pytest.raises(ValueError, match="qpos"):
        w.write_episode({**_meta("bad"), "length": 4}, arrays)
    w.abort()
