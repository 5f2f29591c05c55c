"""The frame-only success classifier (stages.train_wm.success_head) learns from one frame alone."""
import numpy as np
import pytest
import torch

from stages.tokenize.lfq import tokens_to_codes
from stages.train_wm.data import Episode
from stages.train_wm.evaluate import auroc
from stages.train_wm.success_head import SuccessHead, labelled_frames, success_prob, train_success_head


def _episode(i: int, success: bool, rng) -> Episode:
    t = 6
    tokens = rng.integers(0, 16, size=(t + 1, 4)).astype(np.int64)  # 4 bits, a 2x2 grid
    done = np.zeros(t + 1, np.float32)
    if success:
        done[-1] = 1.0
    tokens[:, 0] = np.where(done > 0, 15, 0)  # success shows in the frame: token 15 in the top-left cell
    return Episode(f"e{i}", "x", "ind", tokens, np.zeros((t, 7), np.float32), done, np.zeros((t + 1, 10), np.float32))


def _codes(tokens: np.ndarray) -> torch.Tensor:  # (n, 4) ids -> (n, 4 bits, 2, 2) +-1
    return tokens_to_codes(torch.from_numpy(tokens).view(len(tokens), 2, 2), 4).float()


def test_success_head_reads_success_from_the_frame():
    rng = np.random.default_rng(0)
    eps = [_episode(i, i % 2 == 0, rng) for i in range(20)]
    codes, labels = labelled_frames(eps, _codes)
    assert codes.shape == (20 * 7, 4, 2, 2) and float(labels.sum()) == 10  # one success frame per successful episode
    head = SuccessHead(4, (2, 2), width=8, hidden=16)
    train_success_head(head, (codes, labels), steps=150, batch_size=32, lr=3e-3, seed=0)
    held = [_episode(100 + i, i % 2 == 0, rng) for i in range(10)]
    codes, labels = labelled_frames(held, _codes)
    assert auroc(success_prob(head, codes).numpy(), labels.numpy()) > 0.99


def test_success_head_needs_both_classes():
    rng = np.random.default_rng(0)
    codes, labels = labelled_frames([_episode(0, False, rng)], _codes)
    with pytest.raises(ValueError, match="both classes"):
        train_success_head(SuccessHead(4, (2, 2)), (codes, labels), steps=1, batch_size=4, lr=1e-3, seed=0)
