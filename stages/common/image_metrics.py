"""PSNR, SSIM and LPIPS between batches of images given as uint8 or floats in [0, 1].

Accepted layouts: (N, H, W, 3) / (H, W, 3) (numpy-style, channels last) or (N, 3, H, W) torch-style.
uint8 inputs (numpy or torch) are scaled by 1/255; float inputs must already be in [0, 1].
Every function returns one value per image, (N,) float32 tensor on CPU.
"""
from __future__ import annotations

import numpy as np
import torch
from pytorch_msssim import ssim as _ssim

from stages.common.lpips import get_lpips


def to_float_nchw(images) -> torch.Tensor:
    """(N, 3, H, W) float32 in [0, 1] from uint8/float images, channels-last or channels-first."""
    t = torch.as_tensor(np.asarray(images)) if not isinstance(images, torch.Tensor) else images
    if t.dim() == 3:
        t = t.unsqueeze(0)
    if t.dim() != 4:
        raise ValueError(f"expected images of shape (N, H, W, 3) or (N, 3, H, W), got {tuple(t.shape)}")
    if t.shape[1] != 3 and t.shape[-1] == 3:
        t = t.permute(0, 3, 1, 2)
    if t.shape[1] != 3:
        raise ValueError(f"expected 3 colour channels, got shape {tuple(t.shape)}")
    if t.dtype == torch.uint8:
        return t.float().div_(255.0)
    return t.float()


def _pair(a, b) -> tuple[torch.Tensor, torch.Tensor]:
    x, y = to_float_nchw(a), to_float_nchw(b)
    if x.shape != y.shape:
        raise ValueError(f"image batches differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    return x, y


@torch.no_grad()
def psnr(a, b, max_val: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image (N,); identical images give +inf."""
    x, y = _pair(a, b)
    mse = (x.cpu() - y.cpu()).pow(2).mean(dim=(1, 2, 3))
    return 10.0 * torch.log10(max_val**2 / mse)


@torch.no_grad()
def ssim(a, b) -> torch.Tensor:
    """Structural similarity per image (N,) with the standard 11x11, sigma 1.5 Gaussian window.

    Images smaller than the window (under 11 px a side) raise, as in pytorch-msssim.
    """
    x, y = _pair(a, b)
    return _ssim(x.cpu(), y.cpu(), data_range=1.0, size_average=False).float()


@torch.no_grad()
def lpips(a, b, device: str = "cpu", batch_size: int = 64) -> torch.Tensor:
    """LPIPS v0.1 AlexNet distance per image (N,), computed in batches of ``batch_size`` on ``device``."""
    x, y = _pair(a, b)
    net = get_lpips(device)
    out = []
    for i in range(0, x.shape[0], batch_size):
        xb = x[i : i + batch_size].to(device) * 2 - 1
        yb = y[i : i + batch_size].to(device) * 2 - 1
        out.append(net(xb, yb).cpu())
    return torch.cat(out) if out else torch.zeros(0)


def summary(a, b, device: str = "cpu") -> dict[str, float]:
    """Mean PSNR (dB, inf-safe: identical pairs are capped at 100), SSIM and LPIPS over a batch."""
    p = psnr(a, b).clamp(max=100.0)
    return {"psnr": float(p.mean()), "ssim": float(ssim(a, b).mean()), "lpips": float(lpips(a, b, device).mean())}
