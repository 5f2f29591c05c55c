"""scripts/wm_disagreement.py: a member that is the world model itself never disagrees; another one does."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.rl.tiny import starts_for, tiny_action_wm, tiny_tokenizer

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))


def _imagined(wm, tok, steps: int = 3) -> tuple[torch.Tensor, np.ndarray]:
    """An imagined episode of ``wm`` under random actions: tokens (N, T+1, h, w), actions (N, T, 7)."""
    tokens0 = torch.as_tensor(np.stack([s.tokens for s in starts_for(tok)]).astype(np.int64))  # (N, h, w)
    n = tokens0.shape[0]
    actions = np.random.default_rng(0).uniform(-0.05, 0.05, (n, steps, 7)).astype(np.float32)
    roll = wm.rollout(n)
    roll.reset(tokens0)
    frames = [tokens0]
    for t in range(steps):
        frames.append(roll.step(torch.as_tensor(actions[:, t])).tokens.long())
    return torch.stack(frames, 1), actions


def test_the_imagining_model_agrees_with_itself_and_its_done_head_reads_the_same():
    from wm_disagreement import member_signals

    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    tokens, actions = _imagined(wm, tok)
    dis, done = member_signals(wm, tokens, actions)
    assert dis.shape == done.shape == (tokens.shape[0], 3)
    assert float(dis.max()) == 0.0  # greedy decoding of the same context: the same frame
    # its done head on the imagined frames is what the rollout itself read there
    roll = wm.rollout(tokens.shape[0])
    roll.reset(tokens[:, 0])
    for t in range(3):
        np.testing.assert_allclose(done[:, t], roll.step(torch.as_tensor(actions[:, t])).done_prob.numpy(), atol=1e-5)


def test_a_differently_initialised_member_disagrees():
    from wm_disagreement import member_signals

    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    other = tiny_action_wm(tok)  # the same weights (tiny_action_wm seeds itself), then perturbed
    gen = torch.Generator().manual_seed(123)
    with torch.no_grad():
        for p in other.net.parameters():
            p.add_(torch.randn(p.shape, generator=gen) * 0.5)
    tokens, actions = _imagined(wm, tok)
    dis, _ = member_signals(other, tokens, actions)
    assert float(dis.mean()) > 0.0


def test_auroc_orders_and_ties():
    from wm_disagreement import auroc

    assert auroc(np.array([2.0, 3.0]), np.array([0.0, 1.0])) == 1.0
    assert auroc(np.array([0.0]), np.array([1.0])) == 0.0
    assert auroc(np.array([1.0]), np.array([1.0])) == pytest.approx(0.5)
    assert auroc(np.array([]), np.array([1.0])) is None


def test_decode_encode_consistency_is_a_fraction_per_frame():
    from wm_disagreement import tokenizer_consistency

    tok = tiny_tokenizer()
    tokens = torch.as_tensor(np.stack([s.tokens for s in starts_for(tok)]).astype(np.int64))[:, None]  # (N, 1, h, w)
    c = tokenizer_consistency(tok, tokens)
    assert c.shape == (tokens.shape[0], 1) and bool(((c >= 0) & (c <= 1)).all())
