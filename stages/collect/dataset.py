"""Read a collect artifact: the episode index, whole episodes, or a stream of frames.

    ds = Dataset(collect_artifact_dir)      # reads episodes.jsonl (or the shards' summaries)
    ds.episodes                             # list[EpisodeMeta]
    ep = ds.load(episode_id)                # Episode of numpy arrays
    for eid, t, frame in ds.iter_frames("third", split="ind"): ...

Only finished shards (``*.mcap``) are read; an unfinished ``*.mcap.tmp`` left by a killed
worker is ignored, so a reader only ever sees whole episodes.
"""
from __future__ import annotations

import base64
import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Iterator

import numpy as np

from stages.collect import mcap_io

INDEX_FILE = "episodes.jsonl"
SHARD_DIR = "shards"
SIM_FACTS = "sim.json"


@dataclass(frozen=True)
class SimFacts:
    """How the collect stage rendered and controlled the simulator: every later simulator must match."""

    image_size: int
    robot_mesh: str
    control_mode: str = "pd_ee_delta_pose"


def write_sim_facts(out_dir: Path, facts: SimFacts) -> None:
    (Path(out_dir) / SIM_FACTS).write_text(json.dumps(asdict(facts), indent=1) + "\n")


def read_sim_facts(collect_dir: str | Path) -> SimFacts:
    """The collect artifact's ``sim.json``, with a clear error for artifacts written before it existed."""
    path = Path(collect_dir) / SIM_FACTS
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: the collect artifact predates sim.json; rerun collect "
                                "(python -m pipeline run --force collect)")
    return SimFacts(**json.loads(path.read_text()))


@dataclass(frozen=True)
class EpisodeMeta:
    episode_id: str
    task: str  # pick_place | push | pull | move_to_aim
    instruction: str
    scene_id: str
    object: str
    container: str | None
    table: str
    split: str  # ind | ood
    kind: str  # plans.KINDS: optimal | waypoint_noise | interpolate | grasp_disturb | near_miss | grasp_miss | recover
    seed: int
    success: bool
    length: int  # T, the number of actions
    shard: str  # shard file name under shards/
    start_ns: int = 0  # log time of the episode's first frame in its shard
    end_ns: int = 0  # log time of its last frame (inclusive)
    demo_from: int = 0  # a recovery episode's first action after its deliberate mistake (plans.recover_plan); 0 otherwise

    @staticmethod
    def from_dict(d: dict) -> "EpisodeMeta":
        names = {f.name for f in fields(EpisodeMeta)}
        return EpisodeMeta(**{k: v for k, v in d.items() if k in names})

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Episode:
    meta: EpisodeMeta
    third: np.ndarray  # (T+1, H, W, 3) uint8, frame t observed before action t
    wrist: np.ndarray  # (T+1, H, W, 3) uint8
    action: np.ndarray  # (T, 7) float32, normalized pd_ee_delta_pose action
    ee_pose: np.ndarray  # (T+1, 7) float32, TCP xyz + quaternion wxyz (world frame)
    qpos: np.ndarray  # (T+1, 9) float32
    reward: np.ndarray  # (T,) float32, normalized dense rule reward after each action
    success: np.ndarray  # (T+1,) bool, the task's success check at each frame
    obj_pose: np.ndarray | None = None  # (T+1, 7) float32 object xyz + quaternion wxyz (world); probes only


def write_index(out_dir: Path, metas: list[EpisodeMeta]) -> Path:
    """Write ``episodes.jsonl`` (one EpisodeMeta per line) atomically."""
    path = Path(out_dir) / INDEX_FILE
    tmp = path.with_suffix(".jsonl.tmp")
    tmp.write_text("".join(json.dumps(m.to_dict()) + "\n" for m in metas))
    tmp.replace(path)
    return path


def _scan_shards(root: Path) -> list[EpisodeMeta]:
    metas = []
    for shard in sorted((root / SHARD_DIR).glob(f"*{mcap_io.SHARD_SUFFIX}")):
        for k, m in enumerate(mcap_io.read_episode_metadata(shard)):
            start = k * mcap_io.EPISODE_SPAN_NS  # the writer's slot layout (mcap_io)
            end = start + int(m["length"]) * mcap_io.STEP_NS
            metas.append(EpisodeMeta.from_dict({**m, "shard": shard.name, "start_ns": start, "end_ns": end}))
    return metas


class Dataset:
    """The episodes of a collect artifact directory."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not (self.root / SHARD_DIR).is_dir():
            raise FileNotFoundError(f"{self.root} is not a collect artifact: no {SHARD_DIR}/ directory")
        index = self.root / INDEX_FILE
        if index.is_file():
            self.episodes = [EpisodeMeta.from_dict(json.loads(line)) for line in index.read_text().splitlines() if line]
        else:  # e.g. a partial staging dir after a crash: trust only finished shards
            self.episodes = _scan_shards(self.root)
        self._by_id = {m.episode_id: m for m in self.episodes}

    def __len__(self) -> int:
        return len(self.episodes)

    def meta(self, episode_id: str) -> EpisodeMeta:
        try:
            return self._by_id[episode_id]
        except KeyError:
            raise KeyError(f"episode {episode_id!r} not in {self.root}") from None

    def _shard(self, meta: EpisodeMeta) -> Path:
        return self.root / SHARD_DIR / meta.shard

    def load(self, episode_id: str) -> Episode:
        """All arrays of one episode (reads only its time range of its shard)."""
        m = self.meta(episode_id)
        imgs: dict[str, list] = {v: [] for v in mcap_io.VIEWS}
        steps = []
        for topic, _, msg in mcap_io.iter_messages(self._shard(m), ["/third/image", "/wrist/image", "/step"], m.start_ns, m.end_ns):
            if topic == "/step":
                steps.append(msg)
            else:
                imgs[topic.split("/")[1]].append(mcap_io.decode_png(base64.b64decode(msg["data"])))
        T = m.length
        if len(steps) != T + 1 or any(len(v) != T + 1 for v in imgs.values()):
            raise RuntimeError(f"episode {episode_id} in {self._shard(m)}: expected {T + 1} frames, found "
                               f"{len(steps)} steps / {[len(v) for v in imgs.values()]} images")
        return Episode(
            meta=m,
            third=np.stack(imgs["third"]), wrist=np.stack(imgs["wrist"]),
            action=np.asarray([s["action"] for s in steps[:T]], np.float32).reshape(T, 7),
            ee_pose=np.asarray([s["ee_pose"] for s in steps], np.float32),
            qpos=np.asarray([s["qpos"] for s in steps], np.float32),
            reward=np.asarray([s["reward"] for s in steps[:T]], np.float32),
            success=np.asarray([s["success"] for s in steps], bool),
            obj_pose=np.asarray([s["obj_pose"] for s in steps], np.float32) if "obj_pose" in steps[0] else None,
        )

    def load_states(self, episode_id: str) -> dict[str, np.ndarray]:
        """An episode's states and actions without its images (cheap: no PNG decoding).

        Returns ``ee_pose`` (T+1, 7), ``qpos`` (T+1, 9), ``success`` (T+1,), ``action`` (T, 7),
        ``reward`` (T,) and, in shards that record it, ``obj_pose`` (T+1, 7).
        """
        m = self.meta(episode_id)
        steps = [msg for _, _, msg in mcap_io.iter_messages(self._shard(m), ["/step"], m.start_ns, m.end_ns)]
        if len(steps) != m.length + 1:
            raise RuntimeError(f"episode {episode_id} in {self._shard(m)}: expected {m.length + 1} steps, found {len(steps)}")
        out = {"ee_pose": np.asarray([s["ee_pose"] for s in steps], np.float32),
               "qpos": np.asarray([s["qpos"] for s in steps], np.float32),
               "success": np.asarray([s["success"] for s in steps], bool),
               "action": np.asarray([s["action"] for s in steps[: m.length]], np.float32).reshape(m.length, 7),
               "reward": np.asarray([s["reward"] for s in steps[: m.length]], np.float32)}
        if "obj_pose" in steps[0]:
            out["obj_pose"] = np.asarray([s["obj_pose"] for s in steps], np.float32)
        return out

    def iter_frames(self, view: str = "third", split: str | None = None) -> Iterator[tuple[str, int, np.ndarray]]:
        """Stream (episode_id, t, (H, W, 3) uint8) for every frame of the selected episodes, one
        shard at a time, without holding more than one frame in memory."""
        if view not in mcap_io.VIEWS:
            raise ValueError(f"view must be one of {mcap_io.VIEWS}, got {view!r}")
        if split not in (None, "ind", "ood"):
            raise ValueError(f"split must be None, 'ind' or 'ood', got {split!r}")
        by_shard: dict[str, list[EpisodeMeta]] = {}
        for m in self.episodes:
            if split is None or m.split == split:
                by_shard.setdefault(m.shard, []).append(m)
        for shard, metas in by_shard.items():
            starts = {m.start_ns: m for m in metas}
            for _, log_time, msg in mcap_io.iter_messages(self.root / SHARD_DIR / shard, [f"/{view}/image"]):
                slot = log_time - log_time % mcap_io.EPISODE_SPAN_NS
                m = starts.get(slot)
                if m is not None:
                    yield m.episode_id, (log_time - slot) // mcap_io.STEP_NS, mcap_io.decode_png(base64.b64decode(msg["data"]))
