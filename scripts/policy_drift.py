"""How far PPO moved a policy's deterministic actions from its SFT policy's, on demonstration states.

``ppo/param_change_relative`` in the rl metrics says how much the weights moved, not what the robot
does differently. This script feeds the states of the sft artifact's demonstrations (its held-out
split by default; ``--part train`` for the training one) to the SFT policy and to each rl artifact's
PPO policy, and prints per task and pooled:

- ``flip``: the fraction of states where the gripper decision (the sign of its dim) differs from SFT's;
- ``arm``: the mean change of the translation (dx, dy, dz) relative to the mean size of SFT's;
- ``R2``: the translation's R^2 against the demonstrated actions, SFT's -> PPO's (how much of the
  behaviour cloning survived).

    PYTHONPATH=. .venv/bin/python scripts/policy_drift.py <collect> <tokenize> <sft> <rl> [<rl> ...]

Every rl artifact must have started from that sft artifact. Only the world-model-free parts are
loaded (tokenizer, demonstrations, the two policies); a run takes ~1 minute on one CPU core.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo root: runs without PYTHONPATH=.

TASKS = ("pick_place", "push", "pull", "move_to_aim")


@torch.no_grad()
def mean_actions(policy, obs: dict[str, np.ndarray], batch: int = 1024) -> np.ndarray:
    """(M, 7) deterministic actions (the mean, before execution clips it)."""
    policy.set_training_mode(False)
    n = len(next(iter(obs.values())))
    return torch.cat([policy.mean_action({k: torch.as_tensor(v[i:i + batch]) for k, v in obs.items()})
                      for i in range(0, n, batch)]).numpy()


def drift(sft_actions: np.ndarray, ppo_actions: np.ndarray, demo_actions: np.ndarray) -> dict[str, float]:
    """Gripper flips, relative translation change and translation R^2 (SFT, PPO) over states (M, 7) each."""
    a, b, y = sft_actions, ppo_actions, demo_actions
    var = float(np.mean(y[:, :3].var(0)))
    return {"flip": float(np.mean(np.sign(a[:, 6]) != np.sign(b[:, 6]))),
            "arm": float(np.linalg.norm(b[:, :3] - a[:, :3], axis=1).mean() / np.linalg.norm(a[:, :3], axis=1).mean()),
            "r2_sft": 1.0 - float(np.mean((a[:, :3] - y[:, :3]) ** 2)) / var,
            "r2_ppo": 1.0 - float(np.mean((b[:, :3] - y[:, :3]) ** 2)) / var}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in ("collect", "tokenize", "sft"):
        ap.add_argument(name, type=Path)
    ap.add_argument("rl", type=Path, nargs="+", help="rl artifacts whose PPO started from the sft artifact")
    ap.add_argument("--part", choices=["val", "train"], default="val", help="which of the sft stage's demonstrations")
    args = ap.parse_args()

    from stages.collect.dataset import Dataset
    from stages.sft.data import load_demo, pairs
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, load_policy
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer

    torch.set_num_threads(1)
    ds, store, tok = Dataset(args.collect), TokenStore(args.tokenize), load_tokenizer(args.tokenize, "cpu")
    info = json.loads((args.sft / "policy.json").read_text())
    ids = json.loads((args.sft / "split.json").read_text())[args.part]
    if not ids:
        raise SystemExit(f"{args.sft}: no {args.part} demonstrations (sft.val_fraction 0?); try --part train")
    obs_fn = ObservationFn.for_policy(tok, json.loads((args.sft / "text_embeddings.json").read_text()), info)
    dm = info["demonstrations"]
    demos = [load_demo(ds, store, i, info["frame_skip"], dm["retime_min_move"], dm["retime_max_gap"]) for i in ids]
    obs, demo_actions = pairs(demos, obs_fn)  # obs batch, (M, 7)
    task = np.concatenate([[ds.meta(d.episode_id).task] * len(d.actions) for d in demos])  # (M,)
    sft = mean_actions(load_policy(args.sft / POLICY_FILE), obs)
    print(f"{len(ids)} {args.part} demonstrations, {len(task)} states; per task and all: gripper flips vs SFT, "
          "relative translation change, translation R^2 vs the demonstrations (SFT -> PPO)")
    for rl in args.rl:
        ppo = mean_actions(load_policy(rl / "policy.zip"), obs)
        cells = []
        for t in [*(t for t in TASKS if (task == t).any()), "all"]:
            m = np.ones(len(task), bool) if t == "all" else task == t
            d = drift(sft[m], ppo[m], demo_actions[m])
            cells.append(f"{t} flip {d['flip']:.3f} arm {d['arm']:.2f} R2 {d['r2_sft']:.2f}->{d['r2_ppo']:.2f}")
        print(f"{rl.name[:12]}: " + " | ".join(cells))


if __name__ == "__main__":
    main()
