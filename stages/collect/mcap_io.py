"""MCAP shard files: one per shard, episodes written whole, finished atomically (temp name + rename).

Layout (documented for users in docs/mcap_schema.md):
  - ``/third/image``, ``/wrist/image``: ``foxglove.CompressedImage`` (JSON encoding; ``data`` is
    base64 PNG, lossless so a frame read back equals the frame rendered), one per observed frame;
  - ``/step``: ``roboscape.Step`` (JSON) per observed frame: ee_pose, qpos, obj_pose, success, and the action
    taken / reward received after it (null on the last frame);
  - ``/episode``: ``roboscape.Episode`` (JSON) once at each episode's start, plus an MCAP metadata
    record named ``episode`` with the same fields as strings (readable from the summary alone).
Message log times: episode ``k`` of a shard starts at ``k * EPISODE_SPAN_NS``; frame ``t`` is at
``start + t * STEP_NS`` (20 Hz, the control rate).
"""
from __future__ import annotations

import base64
import json
import os
from pathlib import Path

import cv2
import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

STEP_NS = 50_000_000  # 20 Hz control
EPISODE_SPAN_NS = 10**12  # 1000 s of log time per episode slot: room for 20k steps
SHARD_SUFFIX = ".mcap"
TMP_SUFFIX = ".mcap.tmp"
VIEWS = ("third", "wrist")

COMPRESSED_IMAGE_SCHEMA = {
    "title": "foxglove.CompressedImage",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}
STEP_SCHEMA = {
    "title": "roboscape.Step",
    "type": "object",
    "properties": {
        "episode_id": {"type": "string"},
        "t": {"type": "integer"},
        "ee_pose": {"type": "array", "items": {"type": "number"}, "description": "TCP xyz + quaternion wxyz, world frame"},
        "qpos": {"type": "array", "items": {"type": "number"}},
        "obj_pose": {"type": "array", "items": {"type": "number"},
                     "description": "object centre xyz + quaternion wxyz, world frame (ground truth for probes; never a policy input)"},
        "success": {"type": "boolean"},
        "action": {"type": ["array", "null"], "items": {"type": "number"}, "description": "7-d delta EE action taken after this frame"},
        "reward": {"type": ["number", "null"]},
    },
}
EPISODE_SCHEMA = {"title": "roboscape.Episode", "type": "object", "description": "episode metadata (dataset.EpisodeMeta fields)"}


def encode_png(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def decode_png(data: bytes) -> np.ndarray:
    """(H, W, 3) uint8 RGB."""
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return np.ascontiguousarray(bgr[..., ::-1])


def _floats(a) -> list:
    return [float(v) for v in np.asarray(a, np.float32).reshape(-1)]


class ShardWriter:
    """Writes whole episodes into ``<path>.tmp``; ``close()`` renames it to ``path``."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if not self.path.name.endswith(SHARD_SUFFIX):
            raise ValueError(f"shard path must end with {SHARD_SUFFIX}: {path}")
        self.tmp = self.path.with_name(self.path.name[: -len(SHARD_SUFFIX)] + TMP_SUFFIX)
        self._f = open(self.tmp, "wb")
        self._w = Writer(self._f, compression=CompressionType.ZSTD)
        self._w.start(profile="", library="roboscape-collect")
        img = self._w.register_schema("foxglove.CompressedImage", "jsonschema", json.dumps(COMPRESSED_IMAGE_SCHEMA).encode())
        step = self._w.register_schema("roboscape.Step", "jsonschema", json.dumps(STEP_SCHEMA).encode())
        ep = self._w.register_schema("roboscape.Episode", "jsonschema", json.dumps(EPISODE_SCHEMA).encode())
        self._ch = {v: self._w.register_channel(f"/{v}/image", "json", img) for v in VIEWS}
        self._ch["step"] = self._w.register_channel("/step", "json", step)
        self._ch["episode"] = self._w.register_channel("/episode", "json", ep)
        self.n_episodes = 0

    def write_episode(self, meta: dict, arrays: dict) -> tuple[int, int]:
        """Write one complete episode; returns its (start, end) log time in ns (inclusive)."""
        T = len(arrays["action"])
        for k in ("third", "wrist", "ee_pose", "qpos", "success"):
            if len(arrays[k]) != T + 1:
                raise ValueError(f"episode {meta['episode_id']}: {k} has {len(arrays[k])} rows, expected T+1={T + 1}")
        start = self.n_episodes * EPISODE_SPAN_NS
        eid = meta["episode_id"]
        self._w.add_metadata("episode", {k: json.dumps(v) for k, v in meta.items()})
        self._w.add_message(self._ch["episode"], log_time=start, publish_time=start, data=json.dumps(meta).encode(), sequence=0)
        for t in range(T + 1):
            ts = start + t * STEP_NS
            for v in VIEWS:
                msg = {
                    "timestamp": {"sec": ts // 10**9, "nsec": ts % 10**9},
                    "frame_id": v,
                    "data": base64.b64encode(encode_png(arrays[v][t])).decode(),
                    "format": "png",
                }
                self._w.add_message(self._ch[v], log_time=ts, publish_time=ts, data=json.dumps(msg).encode(), sequence=t)
            step = {
                "episode_id": eid, "t": t, "ee_pose": _floats(arrays["ee_pose"][t]), "qpos": _floats(arrays["qpos"][t]),
                **({"obj_pose": _floats(arrays["obj_pose"][t])} if arrays.get("obj_pose") is not None else {}),
                "success": bool(arrays["success"][t]),
                "action": _floats(arrays["action"][t]) if t < T else None,
                "reward": float(np.float32(arrays["reward"][t])) if t < T else None,
            }
            self._w.add_message(self._ch["step"], log_time=ts, publish_time=ts, data=json.dumps(step).encode(), sequence=t)
        self.n_episodes += 1
        return start, start + T * STEP_NS

    def close(self) -> Path:
        """Finish the file (summary, indexes) and atomically move it into place."""
        self._w.finish()
        self._f.flush()
        os.fsync(self._f.fileno())
        self._f.close()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the unfinished file."""
        self._f.close()
        self.tmp.unlink(missing_ok=True)


def read_episode_metadata(path: Path) -> list[dict]:
    """Episode metadata records of a finished shard, in write order (reads the summary's index)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        return [{k: json.loads(v) for k, v in m.metadata.items()} for m in reader.iter_metadata() if m.name == "episode"]


def iter_messages(path: Path, topics: list[str], start: int | None = None, end: int | None = None):
    """(topic, log_time, decoded JSON) of a shard in log-time order; ``end`` is inclusive."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        for _, channel, message in reader.iter_messages(topics=topics, starting_at=start, ending_at=end):
            yield channel.topic, message.log_time, json.loads(message.data)
