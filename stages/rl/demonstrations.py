"""The sft artifact's demonstration pairs, read the way the sft stage read them.

The sft stage publishes how it read its demonstrations (``policy.json``: ``frame_skip`` and the
``demonstrations`` recipe) and which episodes it trained and validated on (``split.json``, and with
DAgger rounds the planner's continuations in ``dagger_demos/``); the rl
stage's demonstration anchor (``stages.rl.demo_bc``) and filtered BC (``stages.rl.filtered_bc``) read
the same pairs through this one function.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

PARTS = ("train", "val")


def sft_pairs(sft_dir: Path, sft_info: dict, dataset, store, obs_fn, part: str) -> tuple[dict, np.ndarray] | None:
    """``part`` ("train" | "val") of the sft artifact's demonstrations as (obs: key -> (M, ...), actions: (M, 7));
    None when that part is empty (an sft run without held-out demonstrations)."""
    from stages.sft.data import pairs

    demos = sft_demos(sft_dir, sft_info, dataset, store, part)
    return pairs(demos, obs_fn) if demos else None


def sft_demos(sft_dir: Path, sft_info: dict, dataset, store, part: str) -> list:
    """``part`` of the sft artifact's demonstrations (``stages.sft.data.Demo``), read as it read them."""
    from stages.sft import DAGGER_DIR
    from stages.sft.dagger import load_demos
    from stages.sft.data import load_demo

    if part not in PARTS:
        raise ValueError(f"unknown demonstration part {part!r}; expected one of {PARTS}")
    recipe = sft_info.get("demonstrations")
    if recipe is None:
        raise ValueError(f"{sft_dir}/policy.json does not say how its demonstrations were read (no "
                         "'demonstrations' entry: an sft artifact older than that entry); rerun sft")
    ids = json.loads((Path(sft_dir) / "split.json").read_text())[part]
    demos = [load_demo(dataset, store, i, int(sft_info["frame_skip"]), float(recipe["retime_min_move"]),
                       int(recipe["retime_max_gap"])) for i in ids]
    dagger = Path(sft_dir) / DAGGER_DIR
    if part == "train" and dagger.is_dir():  # sft.dagger_rounds: the planner's continuations were trained on too
        demos += load_demos(dagger)
    return demos
