"""Tokenizer network and public API: shapes, save/load round trip, training reduces the loss."""
import numpy as np
import pytest
import torch

from stages.tokenize.model import ModelSpec, TokenizerNet, to_obs
from stages.tokenize.train import TrainSettings, codebook_usage, train
from stages.tokenize.tokenizer import Tokenizer, load_net, load_tokenizer, save_checkpoint
from tokenize_fakes import FakeDataset

TINY = ModelSpec(image_size=32, bits=6, channels=(8, 16), res_blocks=1)


def _frames(n=4, size=32, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 256, size=(n, size, size, 3), dtype=np.uint8), rng.integers(0, 256, size=(n, size, size, 3), dtype=np.uint8))


def test_encode_decode_codes_shapes():
    tok = Tokenizer(TokenizerNet(TINY))
    third, wrist = _frames()
    tokens = tok.encode(third, wrist)
    assert tokens.shape == (4, 8, 8) and tokens.dtype == torch.int64 and tok.grid == (8, 8)
    assert int(tokens.min()) >= 0 and int(tokens.max()) < tok.vocab_size == 64
    t, w = tok.decode(tokens)
    assert t.shape == w.shape == (4, 3, 32, 32) and 0 <= float(t.min()) and float(t.max()) <= 1
    assert tok.codes(tokens).shape == (4, 6, 8, 8)
    # torch uint8 input and other frame sizes (resized to image_size) are accepted
    t64, w64 = _frames(size=64)
    assert tok.encode(torch.from_numpy(t64), torch.from_numpy(w64)).shape == (4, 8, 8)


def test_clear_errors():
    tok = Tokenizer(TokenizerNet(TINY))
    third, wrist = _frames()
    with pytest.raises(ValueError, match="uint8"):
        tok.encode(third.astype(np.float32), wrist)
    with pytest.raises(ValueError, match="differ in shape"):
        tok.encode(third, wrist[:2])
    with pytest.raises(ValueError, match=r"\(N, 8, 8\)"):
        tok.decode(torch.zeros(1, 4, 4, dtype=torch.long))
    with pytest.raises(FileNotFoundError, match="tokenize artifact"):
        load_tokenizer("/nonexistent/tokenize")


def test_save_load_round_trip_gives_identical_tokens(tmp_path):
    torch.manual_seed(0)
    net = TokenizerNet(TINY)
    third, wrist = _frames(8)
    before = Tokenizer(net).encode(third, wrist)
    save_checkpoint(net, tmp_path)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # temp file renamed away
    tok = load_tokenizer(tmp_path)
    assert tok is load_tokenizer(tmp_path)  # loaded once, kept in memory
    assert torch.equal(tok.encode(third, wrist), before)
    assert not tok.net.training
    assert load_net(tmp_path).spec == TINY


def test_training_reduces_reconstruction_loss_on_tiny_synthetic_set():
    ds = FakeDataset(n_ind=4, n_ood=0, T=7, size=32)
    third = np.concatenate([ds.load(e.episode_id).third for e in ds.episodes])
    wrist = np.concatenate([ds.load(e.episode_id).wrist for e in ds.episodes])
    torch.manual_seed(0)
    net = TokenizerNet(TINY)
    settings = TrainSettings(steps=60, batch_size=16, lr=2e-3, warmup_steps=5, weight_decay=0.0, recon_loss="l1",
                             lpips_weight=0.0, lpips_batch=0, entropy_weight=0.1, commitment_weight=0.25, grad_clip=1.0)
    obs = to_obs(torch.from_numpy(third), torch.from_numpy(wrist), 32)
    with torch.no_grad():
        before = (net(obs)[0] - obs).abs().mean().item()
    hist = train(net, third, wrist, settings, seed=0)
    with torch.no_grad():
        after = (net(obs)[0] - obs).abs().mean().item()
    assert after < 0.6 * before, (before, after)
    assert hist.recon[-1] < hist.recon[0]


def test_codebook_usage():
    u = codebook_usage(np.array([0, 0, 1, 1]), bits=2)
    assert u["code_usage"] == 0.5 and u["codes_used"] == 2 and abs(u["code_perplexity"] - 2.0) < 1e-9
