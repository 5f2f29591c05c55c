"""Frame strips (the evaluate stage's rollouts.png, scripts' --strips): frames side by side, not padded."""
import numpy as np
from PIL import Image

from stages.evaluate.report import strip_figure


def test_frames_sit_side_by_side_at_about_a_hundred_pixels_each(tmp_path):
    rng = np.random.default_rng(0)
    rows = [(f"row {i}", rng.integers(0, 255, (8 if i else 5, 64, 64, 3), dtype=np.uint8)) for i in range(3)]
    strip_figure(rows, tmp_path / "s.png", "title")
    # pixels with any colour: the frames' columns; a frame is 100 px wide (1 inch at dpi 100), the gaps ~2 px
    img = np.asarray(Image.open(tmp_path / "s.png").convert("RGB")).astype(int)  # (H, W, 3)
    h, w, _ = img.shape
    assert w == 800
    row = img[int(h * 0.9)]  # a line through the last row's frames
    busy = (np.abs(row - row.mean(axis=1, keepdims=True)).sum(axis=1) > 30)  # (W,) coloured (not white or grey)
    assert busy.mean() > 0.9  # frames cover the width; the old layout left ~20% white between them
    assert h < 3 * (100 + 16) + 35 + 10  # three rows of square frames, their labels and the title
