"""goals.png: per environment, its initial frame, the imagined goal and the ground-truth goal."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def goal_grid(rows: list[tuple[str, list[np.ndarray]]], columns: list[str], path: Path, max_rows: int = 12) -> None:
    """rows: (label, [images (H, W, 3) uint8 or None]) -> a labelled grid saved to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = rows[:max_rows]
    fig, axes = plt.subplots(len(rows), len(columns), figsize=(1.6 * len(columns), 1.5 * len(rows)), squeeze=False)
    for r, (label, images) in enumerate(rows):
        for c, img in enumerate(images):
            ax = axes[r][c]
            ax.axis("off")
            if img is not None:
                ax.imshow(img)
            if r == 0:
                ax.set_title(columns[c], fontsize=7)
        axes[r][0].text(-4, 32, label, fontsize=6, ha="right", va="center")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def to_uint8(x) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8."""
    return (np.clip(np.asarray(x).transpose(1, 2, 0), 0, 1) * 255).round().astype(np.uint8)
