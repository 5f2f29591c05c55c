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
    fig, axes = plt.subplots(len(rows), len(columns), figsize=(2.0 * len(columns), 1.7 * len(rows)), squeeze=False)
    for r, (label, images) in enumerate(rows):
        for c, img in enumerate(images):
            ax = axes[r][c]
            ax.axis("off")
            if img is not None:
                ax.imshow(img)
            ax.set_title(f"{columns[c]}\n{label}" if c == 0 else columns[c], fontsize=6, loc="left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def to_uint8(x) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8."""
    return (np.clip(np.asarray(x).transpose(1, 2, 0), 0, 1) * 255).round().astype(np.uint8)
