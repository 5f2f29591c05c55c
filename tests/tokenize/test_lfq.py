"""Lookup-free quantization: token <-> code round trip, entropy loss, straight-through gradient."""
import math

import pytest
import torch

from stages.tokenize.lfq import LFQ, codes_to_tokens, tokens_to_codes


@pytest.mark.parametrize("bits", [1, 5, 10, 16])
def test_token_ids_round_trip_through_codes(bits):
    g = torch.Generator().manual_seed(bits)
    tokens = torch.randint(0, 2**bits, (3, 4, 5), generator=g)
    codes = tokens_to_codes(tokens, bits)
    assert codes.shape == (3, bits, 4, 5) and set(codes.unique().tolist()) <= {-1.0, 1.0}
    assert torch.equal(codes_to_tokens(codes), tokens)


def test_bit_order_and_range_check():
    codes = -torch.ones(1, 4, 1, 1)
    codes[0, 0] = 1  # channel k is bit k
    codes[0, 2] = 1
    assert codes_to_tokens(codes).item() == 0b0101
    with pytest.raises(ValueError, match=r"\[0, 16\)"):
        tokens_to_codes(torch.tensor([[[16]]]), 4)


def test_quantize_is_sign_and_tokens_match():
    lfq = LFQ(bits=6)
    z = torch.randn(2, 6, 3, 3)
    out = lfq(z)
    assert torch.equal(out.quantized, torch.where(z > 0, 1.0, -1.0))
    assert torch.equal(out.tokens, codes_to_tokens(z))


@pytest.mark.parametrize("bits", [4, 14])  # exact batch entropy and the per-bit approximation
def test_entropy_loss_prefers_uniform_usage_over_collapse(bits):
    lfq = LFQ(bits=bits)
    used_bits = min(bits, 10)  # with 14 bits, 1024 distinct codes vary only the low 10 bits
    n = 2**used_bits
    uniform_tokens = torch.arange(n).view(n, 1, 1) % 2**bits
    uniform = 3.0 * tokens_to_codes(uniform_tokens, bits)  # confident, every code (or bit) used evenly
    collapsed = 3.0 * tokens_to_codes(torch.zeros_like(uniform_tokens), bits)  # confident, one code
    lu, lc = lfq(uniform), lfq(collapsed)
    assert lu.entropy_loss < lc.entropy_loss - 0.5 * used_bits * math.log(2)
    assert lc.batch_entropy < 0.1 and lu.batch_entropy > 0.9 * used_bits * math.log(2)
    unsure = lfq(0.01 * torch.randn(n, bits, 1, 1))  # near the decision boundary: high per-sample entropy
    assert unsure.per_sample_entropy > 0.9 * bits * math.log(2) and unsure.entropy_loss > lu.entropy_loss


def test_exact_batch_entropy_equals_enumerated_code_distribution():
    lfq = LFQ(bits=3, temperature=0.7)
    z = torch.randn(5, 3, 2, 2)
    codes = tokens_to_codes(torch.arange(8).view(8, 1, 1), 3).view(8, 3)  # (K, bits)
    flat = z.permute(0, 2, 3, 1).reshape(-1, 3)
    p = torch.softmax(-((flat[:, None, :] - codes[None]) ** 2).sum(-1) / 0.7, dim=1)  # (P, K) softmax over -distance
    per_sample = -(p * p.log()).sum(1).mean()
    avg = p.mean(0)
    batch = -(avg * avg.log()).sum()
    ps, b = lfq.entropies(z)
    torch.testing.assert_close(ps, per_sample, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(b, batch, rtol=1e-4, atol=1e-5)


def test_straight_through_gradient_reaches_the_latent():
    lfq = LFQ(bits=4)
    z = torch.randn(2, 4, 3, 3, requires_grad=True)
    out = lfq(z)
    (out.quantized * torch.randn_like(out.quantized)).sum().backward()
    assert z.grad is not None and (z.grad != 0).all()  # identity gradient everywhere
    z2 = torch.randn(2, 4, 3, 3, requires_grad=True)
    o2 = lfq(z2)
    (o2.entropy_loss + o2.commitment_loss).backward()
    assert z2.grad.abs().sum() > 0
