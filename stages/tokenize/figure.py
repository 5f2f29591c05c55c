"""The reconstruction figure: real vs reconstructed frame strips for both views."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402


def _strip(images: torch.Tensor) -> np.ndarray:
    """(N, 3, S, S) in [0, 1] -> one (S, N*S, 3) image, frames side by side."""
    return images.clamp(0, 1).permute(2, 0, 3, 1).reshape(images.shape[2], -1, 3).numpy()


def save_recon_figure(path: Path, panels: list[tuple[str, dict[str, torch.Tensor]]]) -> None:
    """Write ``path``: for each (title, {row name: (N, 3, S, S) in [0, 1]}) panel, one strip per row."""
    rows = [(f"{title}: {name}", imgs) for title, p in panels for name, imgs in p.items()]
    if not rows:
        return
    width = max(imgs.shape[0] for _, imgs in rows)
    fig, axes = plt.subplots(len(rows), 1, figsize=(1.1 * width, 1.25 * len(rows)), squeeze=False)
    for ax, (name, imgs) in zip(axes[:, 0], rows):
        ax.imshow(_strip(imgs))
        ax.set_title(name, fontsize=8, loc="left")
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
