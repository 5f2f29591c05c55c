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


def test_fp32_layout_follows_the_timed_probe(monkeypatch):
    """fp32 on a CPU: channels-last only where the probe ran it CHANNELS_LAST_GAIN x faster; once per module."""
    def channels_last(m):
        return m.weight.is_contiguous(memory_format=torch.channels_last) and not m.weight.is_contiguous()

    def timed(m, default_s: float, channels_last_s: float):
        def seconds(call):
            call()
            return channels_last_s if channels_last(m) else default_s
        return seconds

    x = torch.randn(2, 4, 9, 9)
    fast, calls = torch.nn.Conv2d(4, 8, 3), []
    monkeypatch.setattr(precision, "_best_seconds", timed(fast, 1.0, 0.5))
    assert precision.conv_layout(fast, "cpu", "fp32", probe=lambda: calls.append(fast(x))) is fast
    assert precision.layout_of(fast) == "channels_last" and channels_last(fast) and len(calls) == 2  # both layouts timed
    monkeypatch.setattr(precision, "_best_seconds", timed(fast, 1.0, 2.0))
    precision.conv_layout(fast, "cpu", "fp32", probe=lambda: calls.append(fast(x)))
    assert precision.layout_of(fast) == "channels_last" and len(calls) == 2  # decided once per module

    slow = torch.nn.Conv2d(4, 8, 3)
    monkeypatch.setattr(precision, "_best_seconds", timed(slow, 1.0, 1.0 / precision.CHANNELS_LAST_GAIN * 1.01))
    precision.conv_layout(slow, "cpu", "fp32", probe=lambda: slow(x))
    assert precision.layout_of(slow) == "default" and slow.weight.is_contiguous()  # a gain under the bar is not taken
    assert precision.layout_of(torch.nn.Conv2d(4, 8, 3)) == "default"  # never given to conv_layout


def test_a_real_timing_decides_and_keeps_the_values():
    m = torch.nn.Conv2d(4, 8, 3)
    x = torch.randn(2, 4, 9, 9)
    ref = m(x).detach()
    precision.conv_layout(m, "cpu", "fp32", probe=lambda: m(x))
    assert m.chosen_for == "fp32"  # the probe was timed and a layout decided for fp32
    assert torch.allclose(m(x), ref, atol=1e-5)  # whichever layout was kept, the values are the same
