"""Read what a sweep point's committed rl and evaluate artifacts hold into one record."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class PointRun:
    label: str  # short, from the point's axis values: 'reward wm, seed 0'
    method: str  # the rl stage's method (stages.rl.method_of): wm / rule / rule_dense / embedding / proxy
    seed: Any  # the rl stage's seed
    tasks: list[str]
    rl_metrics: dict = field(default_factory=dict)
    rl_dir: Path | None = None  # None: not committed
    eval_dir: Path | None = None
    results: list[dict] = field(default_factory=list)  # evaluated episodes: policy sft / ppo / ppo@<steps>
    snapshots: list[dict] = field(default_factory=list)  # [{timesteps, wall_seconds, ...}] of PPO
    training: list[dict] = field(default_factory=list)  # PPO episodes [{t, wall, return, length, terminated}]
    success_by_start: list[dict] = field(default_factory=list)  # the rl stage's bins [{start_from, start_to, success, interval}]
    seconds: dict[str, float] = field(default_factory=dict)  # stage -> wall seconds of its run
    sft_dir: Path | None = None  # the sft artifact the point's PPO started from

    @property
    def sft_key(self) -> tuple:
        """Points sharing one sft artifact share the SFT policy (it does not depend on the reward)."""
        return (str(self.sft_dir),) if self.sft_dir is not None else (json.dumps(self.seed), tuple(self.tasks))


def _json(path: Path, default: Any) -> Any:
    return json.loads(path.read_text()) if path.is_file() else default


def _jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []


def _committed(path: Path | None) -> Path | None:
    return path if path is not None and (path / "manifest.json").is_file() else None


def _tasks(sft_dir: Path | None) -> list[str]:
    """The tasks the sft stage published in its policy.json (none without a committed sft artifact)."""
    sft_dir = _committed(Path(sft_dir)) if sft_dir is not None else None
    return list(_json(sft_dir / "policy.json", {}).get("tasks", [])) if sft_dir is not None else []


def _short(v: Any) -> str:
    return "+".join(map(str, v)) if isinstance(v, (list, tuple)) else str(v)


def _method(facts: dict, config: dict) -> str:
    """The rl stage's published method (``stages.rl.method_of``); older artifacts: from its reward and config."""
    from stages.rl import method_of
    if "method" in facts:
        return facts["method"]
    reward = facts.get("reward", config.get("reward", "?"))
    return method_of(reward, config.get("rule_terms", "dense"))


def gather(point: dict) -> PointRun | None:
    """``point`` as the engine passes it ({values, label, artifacts}) -> a PointRun, None without rl."""
    arts = point["artifacts"]
    rl_dir = _committed(arts.get("rl"))
    if rl_dir is None:
        return None
    manifest = _json(rl_dir / "manifest.json", {})
    config = manifest.get("key_inputs", {}).get("config", {})
    metrics = _json(rl_dir / "metrics.json", {})
    short = ", ".join(f"{k.rsplit('.', 1)[-1]} {_short(v)}" for k, v in point["values"].items())
    facts = _json(rl_dir / "rl.json", {})  # what the rl stage published (older artifacts: its config)
    run = PointRun(label=short or point["label"], method=_method(facts, config),
                   seed=config.get("seed", point["values"].get("rl.seed")),
                   tasks=_tasks(arts.get("sft")), rl_metrics=metrics, rl_dir=rl_dir,
                   snapshots=_json(rl_dir / "snapshots" / "index.json", []),
                   training=_json(rl_dir / "episodes.json", []), sft_dir=arts.get("sft"),
                   success_by_start=_json(rl_dir / "success_by_start.json", {}).get("bins", []))
    run.seconds["rl"] = float(manifest.get("duration_s", float("nan")))
    play_dir = _committed(arts.get("wm_play"))
    if play_dir is not None:  # the world model's fine-tune on the SFT policy's play, shared by a seed's points
        run.seconds["wm_play"] = float(_json(play_dir / "manifest.json", {}).get("duration_s", float("nan")))
    run.eval_dir = _committed(arts.get("evaluate"))
    if run.eval_dir is not None:
        run.results = _jsonl(run.eval_dir / "results.jsonl")
        run.seconds["evaluate"] = float(_json(run.eval_dir / "manifest.json", {}).get("duration_s", float("nan")))
    return run
