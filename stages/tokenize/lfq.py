"""Lookup-free quantization (LFQ, MAGVIT-2; Yu et al. 2023): each latent channel becomes one bit.

A latent z (B, bits, h, w) is quantised per channel to q = sign(z) in {-1, +1}; the token id at a
position is the bits read as an integer, bit k = channel k (+1 -> 1), so the codebook is implicit
and has 2^bits entries. No codebook lookup means no dead-code problem of VQ-VAE, but the encoder
must still be pushed to *use* the codes, which the entropy loss does:

    entropy loss = E_position[ H(p(code | z)) ]  -  H( E_position[ p(code | z) ] )
                   per-sample entropy (want low:     batch entropy (want high:
                   confident assignments)            all codes used evenly)

with p(code | z) = softmax_c(-||z - c||^2 / tau) over the 2^bits codes c in {-1, +1}^bits. The
squared distance is a sum over channels, so the softmax factorises into independent bits with
p(bit_k = +1) = sigmoid(4 z_k / tau): the per-sample entropy is exactly the sum of per-bit
entropies. The batch entropy needs the full code distribution; it is computed exactly by
enumerating codes when bits <= ``EXACT_BATCH_ENTROPY_MAX_BITS`` and otherwise approximated by the
sum of per-bit marginal entropies (an upper bound, which still rewards balanced bits).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

EXACT_BATCH_ENTROPY_MAX_BITS = 12


@dataclass
class LFQOutput:
    """What ``LFQ.forward`` returns; all losses are scalars."""

    quantized: torch.Tensor  # (B, bits, h, w) +-1 in the forward pass, gradient of z (straight-through)
    tokens: torch.Tensor  # (B, h, w) int64 in [0, 2^bits)
    entropy_loss: torch.Tensor  # per-sample entropy - batch entropy (nats)
    commitment_loss: torch.Tensor  # mean (z - sg[q])^2
    per_sample_entropy: torch.Tensor
    batch_entropy: torch.Tensor


def bit_weights(bits: int, device=None) -> torch.Tensor:
    """(bits,) int64: 2^k for channel k."""
    return 2 ** torch.arange(bits, device=device, dtype=torch.int64)


def codes_to_tokens(codes: torch.Tensor) -> torch.Tensor:
    """Token ids (B, h, w) int64 from +-1 (or any sign-carrying) codes (B, bits, h, w)."""
    bits = codes.shape[1]
    on = (codes > 0).to(torch.int64)  # (B, bits, h, w)
    return (on * bit_weights(bits, codes.device).view(1, bits, 1, 1)).sum(dim=1)


def tokens_to_codes(tokens: torch.Tensor, bits: int) -> torch.Tensor:
    """+-1 float codes (B, bits, h, w) from token ids (B, h, w); inverse of ``codes_to_tokens``."""
    tokens = tokens.to(torch.int64)
    if tokens.numel() and (int(tokens.min()) < 0 or int(tokens.max()) >= 2**bits):
        raise ValueError(f"token ids must lie in [0, {2**bits}) for a {bits}-bit tokenizer, got range [{int(tokens.min())}, {int(tokens.max())}]")
    on = (tokens.unsqueeze(1) // bit_weights(bits, tokens.device).view(1, bits, 1, 1)) % 2  # (B, bits, h, w)
    return on.float() * 2 - 1


def _binary_entropy_from_logits(logit: torch.Tensor) -> torch.Tensor:
    """Entropy (nats) of Bernoulli(sigmoid(logit)), elementwise and numerically stable."""
    p = torch.sigmoid(logit)
    return F.softplus(logit) - p * logit


class LFQ(nn.Module):
    """Lookup-free quantizer with entropy and commitment losses; see the module docstring."""

    def __init__(self, bits: int, temperature: float = 1.0):
        super().__init__()
        if not 1 <= bits <= 16:
            raise ValueError(f"LFQ bits must be in [1, 16] (tokens are stored as uint16), got {bits}")
        self.bits, self.temperature = bits, temperature
        if bits <= EXACT_BATCH_ENTROPY_MAX_BITS:
            all_codes = tokens_to_codes(torch.arange(2**bits).view(-1, 1, 1), bits).view(2**bits, bits)
            self.register_buffer("all_codes", all_codes, persistent=False)  # (K, bits) +-1
        else:
            self.all_codes = None

    def entropies(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean per-sample entropy, batch entropy) in nats for latents z (B, bits, h, w)."""
        logit = 4.0 * z.permute(0, 2, 3, 1).reshape(-1, self.bits) / self.temperature  # (P, bits): log p(+1)/p(-1)
        per_sample = _binary_entropy_from_logits(logit).sum(dim=1).mean()
        if self.all_codes is not None:
            # log p(code) = sum_k log p(bit_k = code_k) = sum_k logsigmoid(code_k * logit_k)
            logp_pos, logp_neg = F.logsigmoid(logit), F.logsigmoid(-logit)  # (P, bits)
            on = (self.all_codes > 0).float()  # (K, bits)
            log_p = logp_pos @ on.T + logp_neg @ (1 - on).T  # (P, K)
            avg_p = log_p.exp().mean(dim=0)  # (K,) average code distribution over positions
            batch = -(avg_p * torch.log(avg_p.clamp_min(1e-12))).sum()
        else:
            marginal = torch.sigmoid(logit).mean(dim=0).clamp(1e-6, 1 - 1e-6)  # (bits,)
            batch = -(marginal * marginal.log() + (1 - marginal) * (1 - marginal).log()).sum()
        return per_sample, batch

    def quantize(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(+-1 codes (B, bits, h, w), token ids (B, h, w)) for latents z; no losses, for inference."""
        if z.dim() != 4 or z.shape[1] != self.bits:
            raise ValueError(f"LFQ expects latents (B, {self.bits}, h, w), got {tuple(z.shape)}")
        q = torch.where(z > 0, torch.ones_like(z), -torch.ones_like(z))  # sign with 0 -> -1, matching token bit 0
        return q, codes_to_tokens(q)

    def forward(self, z: torch.Tensor) -> LFQOutput:
        """Quantise latents z (B, bits, h, w) with a straight-through gradient, plus the LFQ losses."""
        q, tokens = self.quantize(z)
        quantized = z + (q - z).detach()  # forward value q, gradient of the identity
        commitment = F.mse_loss(z, q.detach())
        per_sample, batch = self.entropies(z)
        return LFQOutput(quantized, tokens, per_sample - batch, commitment, per_sample, batch)
