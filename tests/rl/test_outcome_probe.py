"""scripts/outcome_probe.py: a success classifier from the first frame and the arm's path."""
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from outcome_probe import OutcomeNet, batch, fit, peak_probs  # noqa: E402

from stages.train_wm.evaluate import auroc  # noqa: E402


def _episode(rng, success: bool, length: int) -> dict:
    """A path that ends 10 cm right of its start when the episode succeeds, 10 cm left when it fails."""
    end = 1.0 if success else -1.0  # dm
    path = np.zeros((length, 10), np.float32)
    path[:, 0] = np.linspace(0, end, length) + rng.normal(0, 0.02, length)
    label = np.zeros(length, np.float32)
    if success:
        label[-1] = 1.0
    return {"kind": "optimal" if success else "near_miss", "success": success, "label": label, "path": path,
            "codes": np.sign(rng.normal(size=(4, 8, 4))).astype(np.float32), "text": rng.normal(size=384).astype(np.float32)}


def test_batch_pads_with_the_last_state_and_masks_the_padding():
    rng = np.random.default_rng(0)
    eps = [_episode(rng, True, 5), _episode(rng, False, 3)]
    codes, text, path, label, mask = batch(eps)
    assert codes.shape == (2, 4, 8, 4) and text.shape == (2, 384) and path.shape == (2, 5, 10)
    assert mask[1].tolist() == [1, 1, 1, 0, 0] and label[0].tolist() == [0, 0, 0, 0, 1]
    assert torch.equal(path[1, 3], path[1, 2]) and torch.equal(path[1, 4], path[1, 2])


def test_the_classifier_learns_an_outcome_the_path_decides():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    train = [_episode(rng, i % 2 == 0, int(rng.integers(4, 9))) for i in range(64)]
    test = [_episode(rng, i % 2 == 0, int(rng.integers(4, 9))) for i in range(32)]
    net = OutcomeNet(bits=4)
    y = np.array([e["success"] for e in test], dtype=float)
    before = auroc(peak_probs(net, test), y)
    fit(net, train, epochs=15, seed=0)
    after = auroc(peak_probs(net, test), y)
    assert after > 0.95 and after > before
