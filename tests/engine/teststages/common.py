"""What every test stage does: combine its inputs, write outputs and metrics, log its execution."""
from __future__ import annotations

import functools
import json
import os
import random
import time

from pydantic import BaseModel, ConfigDict


class Config(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    value: int = 1
    seed: int = 0
    reward: str = "wm"
    fail: bool = False
    shards: int = 0  # > 0: fan out work with ctx.map
    blob_mb: int = 0  # > 0: also write an output of this many MiB (engine-overhead benchmark)
    skips: list[str] = []  # rl: declared needs this config does not read (unread_needs)


@functools.lru_cache(maxsize=1)
def _cached_model() -> float:
    """Like a loaded tokenizer: built once per process, and building it draws from the seeded RNG."""
    return random.random()


def square(x: int) -> int:
    return x * x


def _checkpointed_half(ctx) -> float | None:
    """With TEST_CHECKPOINT naming this stage (or '*'): a first half of the work kept as a checkpoint,
    computed or resumed (which one goes to TEST_CHECKPOINT_LOG); TEST_CHECKPOINT_FAIL then fails the
    stage after it."""
    if os.environ.get("TEST_CHECKPOINT") not in (ctx.stage, "*"):
        return None
    cp = ctx.checkpoints()
    done = cp.load("half")
    if done is None:
        value = random.random()
        with cp.save("half") as d:
            (d / "half.json").write_text(json.dumps(value))
        how = "computed"
    else:
        value = json.loads((done / "half.json").read_text())
        random.random()  # the draw the first half made, so the later draws match an uninterrupted run's
        how = "resumed"
    log = os.environ.get("TEST_CHECKPOINT_LOG")
    if log:
        with open(log, "a") as f:
            f.write(f"{ctx.stage} {how}\n")
    if os.environ.get("TEST_CHECKPOINT_FAIL") == ctx.stage:
        raise RuntimeError(f"{ctx.stage} failed after its checkpoint")
    return value


def run_stage(ctx) -> None:
    cfg = ctx.config
    log = os.environ.get("TEST_EXEC_LOG")
    if log:
        with open(log, "a") as f:
            f.write(f"{ctx.stage} {os.getpid()} {ctx.jobs}\n")
    inputs = {name: json.loads((path / "result.json").read_text()) for name, path in sorted(ctx.inputs.items())}
    half = _checkpointed_half(ctx)
    # Sleeping is driven by the environment, not the config, so a killed run and its rerun share keys.
    if os.environ.get("TEST_SLEEP_STAGE") in (ctx.stage, "*"):
        (ctx.out / "partial.bin").write_bytes(b"x" * 1024)
        marker = os.environ.get("TEST_MARKER")
        if marker:
            open(marker, "w").close()
        time.sleep(float(os.environ.get("TEST_SLEEP", "30")))
    if cfg.fail:
        raise RuntimeError(f"{ctx.stage} was told to fail")
    shards = ctx.map(square, range(cfg.shards)) if cfg.shards else []
    total = cfg.value + sum(v["total"] for v in inputs.values())
    ctx.log.info("total %d", total)
    _cached_model()
    result = {"stage": ctx.stage, "total": total, "seed": ctx.seed, "draw": random.random(), "reward": cfg.reward, "shards": shards,
              "inputs": sorted(inputs), **({"half": half} if half is not None else {})}
    if cfg.blob_mb:
        with open(ctx.out / "blob.bin", "wb") as f:
            chunk = os.urandom(1 << 20)
            for _ in range(cfg.blob_mb):
                f.write(chunk)
    (ctx.out / "result.json").write_text(json.dumps(result, sort_keys=True))
    ctx.write_metrics({"total": total, "score": total * 10 + ctx.seed, "reward": cfg.reward})
