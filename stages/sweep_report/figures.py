"""The sweep report's figures: success vs training wall time per method (Fig. 2) and PPO training
curves per method (Fig. 3), seeds aggregated."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.evaluate.report import SPLIT_NAMES
from stages.evaluate.stats import wilson


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def success_vs_time(curves: dict[str, dict[str, list[tuple[float, int, int]]]], labels: dict[str, str],
                    path: Path) -> None:
    """curves[method][split] = [(wall seconds, successes, episodes)] -> one panel per split, a line per method."""
    plt = _plt()
    splits = [s for s in ("ind", "ood", "extra") if any(c.get(s) for c in curves.values())]
    fig, axes = plt.subplots(1, len(splits), figsize=(5 * len(splits), 3.4), squeeze=False)
    for ax, split in zip(axes[0], splits):
        for i, (method, by_split) in enumerate(curves.items()):
            pts = sorted(by_split.get(split, []))
            if not pts:
                continue
            w = np.array([wilson(k, n) for _, k, n in pts])  # (P, 3): rate, low, high (high may round below rate at k = n)
            ax.errorbar([p[0] for p in pts], w[:, 0], yerr=np.clip([w[:, 0] - w[:, 1], w[:, 2] - w[:, 0]], 0, None), marker="o",
                        capsize=3, label=labels.get(method, method), alpha=0.85, color=f"C{i}")
        ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel("PPO training wall time (s, mean over seeds); 0 = SFT")
        ax.set_ylabel("success rate (95% Wilson)")
        ax.set_title(f"{SPLIT_NAMES.get(split, split)}: success in the simulator", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def training_curves(curves: dict[str, list[tuple[str, list[dict], list[dict]]]], labels: dict[str, str], path: Path,
                    window: int = 20) -> None:
    """curves[method] = [(seed label, PPO episodes, success-by-start bins)] -> a column per method, a line per
    seed. Top: episode return (rolling mean of ``window`` episodes) over PPO wall time, in each reward's own
    units. Bottom: training success by the step an episode started at (the rl stage's
    ``success_by_start.json``; success as the training reward saw it: the done head's verdict inside the
    world model, the simulator's check in ManiSkill); runs without the file (older artifacts) are left out."""
    plt = _plt()
    methods = [m for m, runs in curves.items() if any(eps for _, eps, _ in runs)]
    if not methods:
        return
    fig, axes = plt.subplots(2, len(methods), figsize=(3.6 * len(methods), 5.6), squeeze=False)
    for col, method in enumerate(methods):
        top, bottom = axes[0, col], axes[1, col]
        for i, (seed, eps, bins) in enumerate(curves[method]):
            color = f"C{i}"
            if eps:
                wall = np.array([e["wall"] for e in eps], dtype=np.float64)  # (E,)
                ret = np.array([e["return"] for e in eps], dtype=np.float64)  # (E,)
                k = min(window, len(ret))
                smooth = np.convolve(ret, np.ones(k) / k, mode="valid")  # (E - k + 1,)
                top.plot(wall, ret, ".", ms=2, alpha=0.25, color=color)
                top.plot(wall[k - 1:], smooth, label=f"seed {seed}", color=color)
            if bins:
                mid = np.array([(b["start_from"] + b["start_to"]) / 2 for b in bins])  # (B,) env steps
                rate = np.array([b["success"] for b in bins])  # (B,)
                lo, hi = np.array([b["interval"] for b in bins]).T  # (B,) each
                bottom.fill_between(mid, lo, hi, alpha=0.15, color=color)
                bottom.plot(mid, rate, "o-", ms=3, label=f"seed {seed}", color=color)
        top.set_title(labels.get(method, method), fontsize=8)
        top.set_xlabel("PPO wall time (s)")
        top.set_ylabel("episode return (own reward)")
        top.legend(fontsize=7)
        bottom.set_ylim(0, 1)
        bottom.set_xlabel("env step the episode started at")
        bottom.set_ylabel("training success (95% Wilson)")
        if bottom.lines:
            bottom.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def rollout_strips(gifs: list[tuple[str, Path]], path: Path, frames: int = 8) -> None:
    """[(caption, GIF)] -> one small image: a row of ``frames`` evenly spaced frames per GIF.

    Evenly spaced over the GIF's frames, not over time: the GIF encoder merges identical consecutive
    frames (a still arm), so a still stretch counts once."""
    from PIL import Image, ImageSequence

    plt = _plt()
    rows = []
    for caption, gif in gifs:
        with Image.open(gif) as im:
            seq = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(im)]  # T x (H, W, 3)
        idx = np.linspace(0, len(seq) - 1, min(frames, len(seq))).round().astype(int)
        gap = np.full((seq[0].shape[0], 4, 3), 255, np.uint8)  # (H, 4, 3) white separator
        strip = np.concatenate([x for i in idx for x in (seq[i], gap)][:-1], axis=1)  # (H, n*W + gaps, 3)
        rows.append((caption, strip))
    if not rows:
        return
    fig, axes = plt.subplots(len(rows), 1, figsize=(8, 1.25 * len(rows)), squeeze=False)
    for ax, (caption, strip) in zip(axes[:, 0], rows):
        ax.imshow(strip)
        ax.axis("off")
        ax.set_title(caption, fontsize=7, loc="left")
    fig.tight_layout(pad=0.3)
    fig.savefig(path, dpi=90)
    plt.close(fig)
