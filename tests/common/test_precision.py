"""Mixed-precision choice: explicit modes pass through, auto decides by measurement, bad names fail."""
import contextlib

import pytest
import torch

from stages.common import precision


def test_explicit_modes_and_errors():
    assert precision.resolved("cpu", "fp32") == "fp32" and precision.resolved("cpu", "bf16") == "bf16"
    assert precision.resolved("cuda", "auto") == "bf16"
    with pytest.raises(ValueError, match="precision must be"):
        precision.resolved("cpu", "half")
    assert isinstance(precision.autocast("cpu", "fp32"), contextlib.nullcontext)


def test_auto_follows_the_measured_cpu_speedup(monkeypatch):
    monkeypatch.setattr(precision, "cpu_bf16_speedup", lambda: 1.0)
    assert precision.resolved("cpu", "auto") == "fp32"
    monkeypatch.setattr(precision, "cpu_bf16_speedup", lambda: 5.0)
    assert precision.resolved("cpu", "auto") == "bf16"
    with precision.autocast("cpu", "auto"):
        y = torch.nn.Linear(8, 8)(torch.randn(2, 8))
    assert y.dtype == torch.bfloat16


def test_conv_layout_is_channels_last_only_for_bf16_on_cpu():
    def conv():
        return torch.nn.Conv2d(4, 8, 3)

    def channels_last(m):
        return m.weight.is_contiguous(memory_format=torch.channels_last) and not m.weight.is_contiguous()

    assert not channels_last(precision.conv_layout(conv(), "cpu", "fp32"))
    m = conv()
    assert precision.conv_layout(m, "cpu", "bf16") is m and channels_last(m)
    x = torch.randn(2, 4, 9, 9)
    ref = conv()
    fast = precision.conv_layout(conv(), "cpu", "bf16")
    fast.load_state_dict(ref.state_dict())
    assert torch.allclose(fast(x), ref(x), atol=1e-5)  # the layout changes speed, not values
