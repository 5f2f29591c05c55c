"""Does the policy's observation carry the task? A probe that reads the object's and the TCP's
position from it.

For each candidate observation, a small regressor is fitted on the world-model frames
(every ``frame_skip``-th control step) of the IND training episodes to regress the object's centre
and the TCP position (metres, world frame, from the collect artifact's recorded states), and its
error is measured on held-out IND episodes and on OOD episodes (unseen objects), in cm
(Euclidean, xyz), over all their frames and over their first frames only. The first frames are
the honest test for the object: later in a demonstration the gripper sits at the object, so the
TCP alone predicts where the object is; at t = 0 the robot is at rest and only the image can.
Two regressors: an MLP with one hidden layer on the flattened input, and (for inputs with the
latent) the policy's own image path, a two-layer CNN over the token grid with dropout 0.3, whose
error is what the policy's architecture can read. Candidates, for every tokenize artifact given:

    codes            the tokenizer's +-1 latent alone (what the policy saw before proprioception)
    codes+proprio    the latent next to the robot's proprioception (stages.common.proprio)
    proprio          proprioception alone (a floor: it cannot know where the object is)

    PYTHONPATH=. .venv/bin/python benchmarks/observation_probe.py <collect> <tokenize> [<tokenize> ...]

Every number comes from this one run; the ranking between candidates is what it is for.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn


def frames_of(ds, store, tok, ids: list[str], frame_skip: int) -> dict[str, np.ndarray]:
    """codes (M, bits*h*w), proprio (M, 10), object xyz (M, 3), tcp xyz (M, 3) of the kept frames of ``ids``."""
    from stages.common.frame_skip import frame_indices
    from stages.common.proprio import proprio_from_state

    codes, prop, obj, tcp, first = [], [], [], [], []
    for i in ids:
        st = ds.load_states(i)
        if "obj_pose" not in st:
            raise SystemExit(f"episode {i} has no recorded object pose: collect with this version of the code")
        idx = frame_indices(len(st["action"]), frame_skip)
        tokens = torch.from_numpy(np.asarray(store.episode(i), dtype=np.int64)[idx])
        codes.append(tok.codes(tokens).reshape(len(idx), -1).numpy())
        prop.append(proprio_from_state(st["ee_pose"][idx], st["qpos"][idx]))
        obj.append(st["obj_pose"][idx, :3]), tcp.append(st["ee_pose"][idx, :3])
        first.append(np.arange(len(idx)) == 0)
    cat = np.concatenate
    return {"codes": cat(codes).astype(np.float32), "proprio": cat(prop), "obj": cat(obj), "tcp": cat(tcp),
            "first": cat(first)}


def features(d: dict, kind: str) -> np.ndarray:
    return {"codes": d["codes"], "proprio": d["proprio"],
            "codes+proprio": np.concatenate([d["codes"], d["proprio"]], 1)}[kind]


class GridProbe(nn.Module):
    """The policy's image path (stages.sft.policy.LatentExtractor's CNN) on the latent part of x, + the rest."""

    def __init__(self, bits: int, grid: tuple[int, int], extra: int, out: int):
        super().__init__()
        self.shape, self.n = (bits, *grid), bits * grid[0] * grid[1]
        self.cnn = nn.Sequential(nn.Conv2d(bits, 64, 3, padding=1), nn.GELU(), nn.Conv2d(64, 64, 3, stride=2, padding=1),
                                 nn.GELU(), nn.Flatten(), nn.Dropout(0.3))
        flat = 64 * ((grid[0] + 1) // 2) * ((grid[1] + 1) // 2)
        self.head = nn.Sequential(nn.Linear(flat + extra, 256), nn.GELU(), nn.Linear(256, out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        img = self.cnn(x[:, : self.n].reshape(len(x), *self.shape))
        return self.head(torch.cat([img, x[:, self.n:]], 1))


def fit_probe(x: np.ndarray, y: np.ndarray, seed: int, steps: int = 3000, hidden: int = 256,
              grid: tuple[int, int, int] | None = None) -> nn.Module:
    """A regressor x -> y (standardised targets), AdamW, minibatches of 256: an MLP, or ``GridProbe``
    when ``grid`` = (bits, h, w) says the first bits*h*w inputs are a token grid's codes."""
    torch.manual_seed(seed)
    x_t, y_t = torch.from_numpy(x), torch.from_numpy(y.astype(np.float32))
    mu, sd = y_t.mean(0), y_t.std(0).clamp_min(1e-6)
    if grid is None:
        net = nn.Sequential(nn.Linear(x.shape[1], hidden), nn.GELU(), nn.Linear(hidden, y.shape[1]))
    else:
        bits, h, w = grid
        net = GridProbe(bits, (h, w), x.shape[1] - bits * h * w, y.shape[1])
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=1e-2 if grid else 1e-3)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(0, len(x_t), (256,), generator=gen)
        loss = ((net(x_t[idx]) - (y_t[idx] - mu) / sd) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    net.mu, net.sd = mu, sd
    return net


def errors_cm(net: nn.Module, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Euclidean errors (cm) of the probe on each row."""
    with torch.no_grad():
        pred = net(torch.from_numpy(x)) * net.sd + net.mu
    return 100 * np.linalg.norm(pred.numpy() - y, axis=1)


def mean_ci(e: np.ndarray) -> tuple[float, float]:
    """Mean and normal 95% half-width (frames of one episode are correlated: read it as a lower bound)."""
    return float(e.mean()), float(1.96 * e.std(ddof=1) / np.sqrt(len(e)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("collect", type=Path)
    ap.add_argument("tokenize", type=Path, nargs="+")
    ap.add_argument("--frame-skip", type=int, default=4)
    ap.add_argument("--max-episodes", type=int, default=400, help="IND training episodes the probe is fitted on")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="also write the table as JSON")
    args = ap.parse_args()
    torch.set_num_threads(2)

    from stages.collect.dataset import Dataset
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer

    ds = Dataset(args.collect)
    rows = []
    for tok_dir in args.tokenize:
        t0 = time.perf_counter()
        split = json.loads((tok_dir / "split.json").read_text())
        rng = np.random.default_rng(args.seed)
        train_ids = list(split["train"])
        train_ids = [train_ids[i] for i in sorted(rng.choice(len(train_ids), min(args.max_episodes, len(train_ids)), replace=False))]
        ood_ids = [m.episode_id for m in ds.episodes if m.split == "ood"]
        tok, store = load_tokenizer(tok_dir), TokenStore(tok_dir)
        data = {name: frames_of(ds, store, tok, ids, args.frame_skip)
                for name, ids in (("train", train_ids), ("heldout_ind", split["heldout"]), ("ood", ood_ids))}
        label = f"{tok_dir.name[:12]} grid {list(tok.grid)} x {tok.bits} bits"
        for kind, probe in (("codes", "mlp"), ("codes", "cnn"), ("codes+proprio", "cnn"), ("proprio", "mlp")):
            row = {"tokenizer": label, "observation": kind, "probe": probe, "train_frames": len(data["train"]["obj"])}
            grid = (tok.bits, *tok.grid) if probe == "cnn" else None
            for target in ("obj", "tcp"):
                net = fit_probe(features(data["train"], kind), data["train"][target], args.seed, args.steps, grid=grid)
                for sp in ("heldout_ind", "ood"):
                    e = errors_cm(net, features(data[sp], kind), data[sp][target])
                    row[f"{target}/{sp}"], row[f"{target}/{sp}/ci95"] = mean_ci(e)
                    row[f"{target}/{sp}/first"], row[f"{target}/{sp}/first/ci95"] = mean_ci(e[data[sp]["first"]])
            rows.append(row)
            print(f"{label:36s} {kind:14s} {probe}  object IND {row['obj/heldout_ind']:5.2f} (t=0 {row['obj/heldout_ind/first']:5.2f}) cm, "
                  f"OOD {row['obj/ood']:5.2f} (t=0 {row['obj/ood/first']:5.2f}) cm | "
                  f"TCP IND {row['tcp/heldout_ind']:5.2f} cm, OOD {row['tcp/ood']:5.2f} cm", flush=True)
        print(f"  ({time.perf_counter() - t0:.0f} s, {len(data['train']['obj'])} training frames, "
              f"{len(data['heldout_ind']['obj'])} held-out IND, {len(data['ood']['obj'])} OOD)", flush=True)
    # what predicting the mean position would score, for scale
    base = data["train"]["obj"].mean(0)
    for sp in ("heldout_ind", "ood"):
        e = 100 * np.linalg.norm(data[sp]["obj"] - base, axis=1)
        print(f"object at its mean training position, {sp}: {e.mean():.2f} cm (t=0 {e[data[sp]['first']].mean():.2f} cm)")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
