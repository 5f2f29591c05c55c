"""``frames.png``: real vs world-model-predicted frame strips (open loop from a real start frame)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

COLUMNS = (0, 1, 3, 5, 10, 15)  # horizons shown (0 = the real start frame)


def frame_strips(panels: list[tuple[str, dict[str, torch.Tensor]]], path: Path) -> None:
    """One row per named strip of each panel; each strip is (H+1, 3, S, 2S) in [0, 1], index = horizon."""
    cols = [c for c in COLUMNS if all(c < s.shape[0] for _, rows in panels for s in rows.values())]
    n_rows = sum(len(rows) for _, rows in panels)
    fig, axes = plt.subplots(n_rows, len(cols), figsize=(2.4 * len(cols), 1.4 * n_rows), squeeze=False)
    row = 0
    for p, (title, rows) in enumerate(panels):
        for r, (name, imgs) in enumerate(rows.items()):
            for c, hz in enumerate(cols):
                ax = axes[row, c]
                ax.imshow(imgs[hz].permute(1, 2, 0).clamp(0, 1).numpy())
                ax.set_xticks([])
                ax.set_yticks([])
                if c == 0:
                    ax.set_ylabel(f"{title}\n{name}", fontsize=7)
                if p == 0 and r == 0:
                    ax.set_title(f"t+{hz}", fontsize=9)
            row += 1
    fig.suptitle("open-loop rollouts from a real start frame: action WM under the recorded actions, "
                 "text WM under the instruction (third | wrist view)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
