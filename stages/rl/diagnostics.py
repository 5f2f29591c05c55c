"""Reward diagnostics (paper Fig. 3, made quantitative): every reward module's reward along
held-out successful trajectories, IND and OOD, and its Spearman correlation with progress.

A good reward rises as a successful episode progresses; ``spearman`` is the mean over episodes of
the rank correlation between a module's per-frame reward and normalised time t/T.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from stages.rl.rewards.fit import FrameSet


def progress_correlation(reward: np.ndarray, progress: np.ndarray, episode: np.ndarray) -> float:
    """Mean per-episode Spearman correlation of reward with progress (NaN-free episodes only)."""
    rhos = []
    for e in np.unique(episode):
        m = episode == e
        if m.sum() < 3 or np.ptp(reward[m]) == 0:
            continue
        rhos.append(spearmanr(reward[m], progress[m]).statistic)
    return float(np.mean(rhos)) if rhos else float("nan")


def binned_curve(reward: np.ndarray, progress: np.ndarray, bins: int = 10) -> np.ndarray:
    """Mean reward per progress bin, (bins,)."""
    idx = np.minimum((progress * bins).astype(int), bins - 1)
    return np.array([reward[idx == b].mean() if (idx == b).any() else np.nan for b in range(bins)])


def plot_curves(curves: dict[str, dict[str, np.ndarray]], path: Path) -> None:
    """curves[split][module] = (bins,) mean reward -> one panel per split, min-max normalised per module."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(curves), figsize=(4.2 * len(curves), 3.2), squeeze=False)
    for ax, (split, per_module) in zip(axes[0], curves.items()):
        for name, c in per_module.items():
            lo, hi = np.nanmin(c), np.nanmax(c)
            norm = (c - lo) / (hi - lo) if hi > lo else np.zeros_like(c)
            ax.plot(np.linspace(0.05, 0.95, len(c)), norm, marker="o", ms=3, label=name)
        ax.set_title(f"{split}: reward along successful episodes", fontsize=9)
        ax.set_xlabel("progress t / T")
        ax.set_ylabel("mean reward (min-max normalised)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
