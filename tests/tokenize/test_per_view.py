"""The per-view layout: one grid per camera, third view on top, shared weights."""
from __future__ import annotations

import torch

from stages.tokenize.lfq import tokens_to_codes
from stages.tokenize.model import ModelSpec, TokenizerNet


def test_per_view_grid_keeps_each_camera_in_its_own_half():
    torch.manual_seed(0)
    net = TokenizerNet(ModelSpec(image_size=32, bits=6, channels=(8, 16), per_view=True)).eval()
    assert net.spec.grid == (16, 8)
    obs = torch.rand(3, 6, 32, 32) * 2 - 1
    ids = net.encode(obs)
    assert ids.shape == (3, 16, 8)
    swapped = net.encode(torch.cat([obs[:, 3:], obs[:, :3]], 1))
    assert torch.equal(swapped[:, :8], ids[:, 8:]) and torch.equal(swapped[:, 8:], ids[:, :8])
    # changing the wrist view leaves the third view's tokens alone (not so when the views share a grid)
    other = obs.clone()
    other[:, 3:] = torch.rand(3, 3, 32, 32) * 2 - 1
    assert torch.equal(net.encode(other)[:, :8], ids[:, :8])
    recon = net.decode_codes(tokens_to_codes(ids, 6))
    assert recon.shape == (3, 6, 32, 32)
    r, q = net(obs)
    assert r.shape == obs.shape and q.quantized.shape == (3, 6, 16, 8)


def test_stacked_layout_is_unchanged():
    net = TokenizerNet(ModelSpec(image_size=32, bits=6, channels=(8, 16), per_view=False)).eval()
    assert net.spec.grid == (8, 8) and net.encode(torch.zeros(2, 6, 32, 32)).shape == (2, 8, 8)
