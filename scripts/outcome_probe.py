"""Can success be read from what the world model gets right: the real first frame and the arm's path?

The imagined frames lose the object (docs/RESULTS.md), but the first frame is real and the
proprioception head tracks the TCP to ~0.5 cm after 5 steps. This probe fits a small classifier of
"success by step t" from (first-frame tokens, proprioception at steps 0..t, instruction) on the
collected episodes at the policy's step (every ``frame_skip``-th control step; failures are the
collect's near-miss and grasp-miss kinds) and reads it on held-out IND and OOD collected episodes:
per-episode AUROC of the peak probability, and precision / recall at thresholds, per kind.

    PYTHONPATH=. .venv/bin/python scripts/outcome_probe.py <collect> <tokenize> <sft> [--epochs 30] [--out F.pt]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from torch import nn


class OutcomeNet(nn.Module):
    """codes (B, bits, h, w) + instruction (B, 384) + proprio path (B, T, 10) -> success logit per step (B, T)."""

    def __init__(self, bits: int, text_dim: int = 384, width: int = 64):
        super().__init__()
        self.cnn = nn.Sequential(nn.Conv2d(bits, 32, 3, padding=1), nn.GELU(), nn.Conv2d(32, 32, 3, padding=1), nn.GELU(),
                                 nn.AdaptiveAvgPool2d((4, 2)), nn.Flatten(), nn.Linear(32 * 8, width))
        self.text = nn.Linear(text_dim, width)
        self.inp = nn.Linear(20, width)
        self.gru = nn.GRU(width, width, batch_first=True)
        self.head = nn.Sequential(nn.Linear(3 * width, width), nn.GELU(), nn.Linear(width, 1))

    def forward(self, codes, text, path):
        ctx = torch.cat([self.cnn(codes), self.text(text)], -1)  # (B, 2W)
        x = torch.cat([path, path - path[:, :1]], -1)  # (B, T, 20) absolute and relative to the start
        h, _ = self.gru(self.inp(x))  # (B, T, W)
        return self.head(torch.cat([h, ctx[:, None].expand(-1, h.shape[1], -1)], -1)).squeeze(-1)


def episodes(ds, store, frame_skip: int, ids: list[str], tok, text: dict) -> list[dict]:
    """Collected episodes ``ids`` (a ``Dataset`` and its ``TokenStore``) at the policy's step."""
    from stages.common.proprio import proprio_from_state

    out = []
    for eid in ids:
        m, st = ds.meta(eid), ds.load_states(eid)
        idx = np.arange(0, m.length + 1, frame_skip)
        prop = proprio_from_state(st["ee_pose"][idx], st["qpos"][idx])  # (T+1, 10)
        succ = np.maximum.accumulate(st["success"][idx].astype(np.float32))  # (T+1,) success by step t
        first = np.asarray(store.episode(eid)[0], np.int64)[None]  # (1, h, w)
        out.append({"id": eid, "task": m.task, "kind": m.kind, "success": bool(m.success),
                    "codes": tok.codes(first)[0].numpy(), "text": np.asarray(text[m.instruction], np.float32),
                    "path": prop.astype(np.float32), "label": succ})
    return out


def batch(eps: list[dict]):
    t = max(len(e["path"]) for e in eps)
    path = np.zeros((len(eps), t, 10), np.float32)
    label = np.zeros((len(eps), t), np.float32)
    mask = np.zeros((len(eps), t), np.float32)
    for i, e in enumerate(eps):
        n = len(e["path"])
        path[i, :n], label[i, :n], mask[i, :n] = e["path"], e["label"], 1
        path[i, n:] = e["path"][-1]
    return (torch.as_tensor(np.stack([e["codes"] for e in eps])), torch.as_tensor(np.stack([e["text"] for e in eps])),
            torch.as_tensor(path), torch.as_tensor(label), torch.as_tensor(mask))


def fit(net: OutcomeNet, train: list[dict], epochs: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-2)
    pos = sum(float(e["label"].sum()) for e in train)
    tot = sum(len(e["label"]) for e in train)
    w_pos = (tot - pos) / max(pos, 1.0)  # class balance over steps
    for ep in range(epochs):
        net.train()
        order = rng.permutation(len(train))
        losses = []
        for i in range(0, len(order), 32):
            codes, text, path, label, mask = batch([train[j] for j in order[i:i + 32]])
            logit = net(codes, text, path)
            w = mask * (1 + (w_pos - 1) * label)
            loss = (nn.functional.binary_cross_entropy_with_logits(logit, label, reduction="none") * w).sum() / w.sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
        if ep % 5 == 4 or ep == epochs - 1:
            print(f"  epoch {ep + 1}: loss {np.mean(losses):.3f}", flush=True)


@torch.no_grad()
def peak_probs(net: OutcomeNet, eps: list[dict]) -> np.ndarray:
    net.eval()
    out = []
    for i in range(0, len(eps), 64):
        codes, text, path, _, mask = batch(eps[i:i + 64])
        p = torch.sigmoid(net(codes, text, path)) * mask
        out.append(p.max(1).values.numpy())
    return np.concatenate(out)


def report(name: str, p: np.ndarray, eps: list[dict]) -> None:
    from stages.train_wm.evaluate import auroc

    y = np.array([e["success"] for e in eps])
    print(f"{name}: {len(eps)} episodes ({y.sum()} successes), AUROC of the peak {auroc(p, y.astype(float)):.3f}")
    for th in (0.5, 0.7, 0.9):
        fire = p >= th
        prec = (fire & y).sum() / max(fire.sum(), 1)
        print(f"  theta {th}: fires {fire.sum()}, precision {prec:.2f}, recall {(fire & y).sum() / max(y.sum(), 1):.2f}")
    for kind in sorted({e["kind"] for e in eps}):
        k = np.array([e["kind"] == kind for e in eps])
        print(f"    {kind:15s} n {k.sum():3d}  fires at 0.5: {(p[k] >= 0.5).mean():.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("collect", type=Path)
    ap.add_argument("tokenize", type=Path)
    ap.add_argument("sft", type=Path)
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)

    from stages.collect.dataset import Dataset
    from stages.sft import read_policy_json
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer

    info = read_policy_json(args.sft)
    text = json.loads((args.sft / "text_embeddings.json").read_text())
    tok = load_tokenizer(args.tokenize, "cpu")
    split = json.loads((args.tokenize / "split.json").read_text())
    ds, store = Dataset(args.collect), TokenStore(args.tokenize)
    ood = [m.episode_id for m in ds.episodes if m.split == "ood"]
    fs = int(info["frame_skip"])
    train, held, oods = (episodes(ds, store, fs, ids, tok, text) for ids in (split["train"], split["heldout"], ood))
    net = OutcomeNet(tok.bits)
    fit(net, train, args.epochs, args.seed)
    for name, eps in (("train", train), ("held-out IND", held), ("OOD", oods)):
        report(name, peak_probs(net, eps), eps)
    if args.out:
        torch.save(net.state_dict(), args.out)


if __name__ == "__main__":
    main()
