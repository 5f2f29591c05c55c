"""Held-out IND and OOD reconstruction of several tokenizer checkpoints, scored on the same frames.

    .venv/bin/python scripts/compare_tokenizers.py <collect dir> <tokenize split.json> <tokenizer dir> [<tokenizer dir> ...]
        [--frames 512] [--seed 1]

Each tokenizer dir holds a ``tokenizer.pt`` (a tokenize artifact, or a copy of one). Frames come
from the split file's held-out IND episodes and from every OOD episode, sampled as the tokenize
stage samples its evaluation frames, and are scored by the stage's own ``evaluate``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    from stages.tokenize import _episodes_for_frames, _load_frames, open_dataset
    from stages.tokenize.tokenizer import load_net
    from stages.tokenize.train import evaluate

    ap = argparse.ArgumentParser()
    ap.add_argument("collect")
    ap.add_argument("split_json")
    ap.add_argument("tokenizers", nargs="+")
    ap.add_argument("--frames", type=int, default=512)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(1)
    ds = open_dataset(args.collect)
    held_ids = set(json.loads(Path(args.split_json).read_text())["heldout"])
    splits = {"heldout_ind": [e for e in ds.episodes if e.episode_id in held_ids],
              "ood": [e for e in ds.episodes if e.split == "ood"]}
    nets = {d: load_net(d).eval() for d in args.tokenizers}
    for split, eps in splits.items():
        rng = np.random.default_rng(args.seed)
        third, wrist = _load_frames(ds, _episodes_for_frames(rng, eps, args.frames), args.frames, rng)
        for d, net in nets.items():
            m = evaluate(net, third, wrist)
            print(f"{split} ({len(third)} frames) {d}: " + ", ".join(f"{k} {v:.4f}" for k, v in m.items()), flush=True)


if __name__ == "__main__":
    main()
