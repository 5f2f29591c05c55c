"""scripts/wm_confidence_probe.py: its rollout records a confidence per frame and decodes as the plain one."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.rl.tiny import starts_for, tiny_action_wm, tiny_tokenizer

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))


def test_the_confident_rollout_decodes_the_same_frames_and_keeps_a_probability_per_frame():
    from wm_confidence_probe import confident_rollout_class

    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    tokens0 = torch.as_tensor(np.stack([s.tokens for s in starts_for(tok)]).astype(np.int64))  # (3, h, w)
    actions = torch.zeros(3, 7)
    plain, probed = wm.rollout(3), confident_rollout_class()(wm, 3)
    plain.reset(tokens0), probed.reset(tokens0)
    for _ in range(2):
        assert torch.equal(plain.step(actions).tokens, probed.step(actions).tokens)
    assert len(probed.confidence) == 2
    for c in probed.confidence:
        assert c.shape == (3,) and bool(((c > 0) & (c <= 1)).all())


def test_spearman_is_one_for_a_monotone_relation_and_minus_one_for_a_reversed_one():
    from wm_confidence_probe import spearman

    x = np.array([0.1, 0.5, 0.2, 0.9])
    assert spearman(x, x**3) == pytest.approx(1.0) and spearman(x, -x) == pytest.approx(-1.0)
