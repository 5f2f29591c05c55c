"""Eight of the benchmarks under benchmarks/ run, each at its smallest size through its real entry point.

They are not timed here (ratios are theirs to print); this only keeps them from rotting when the
code they call changes (two had gone stale when the helpers they import gained a device). The
others (collect_throughput, engine_overhead, observation_probe, wm_rollout) are not run here.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run(*args: str) -> str:
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_wm_precision_prints_its_ratios():
    out = run("benchmarks/wm_precision.py", "--envs", "1")
    assert "world-model rollout step" in out and "ratio" in out


@pytest.mark.sim
def test_sim_episode_prints_its_ratios():
    out = run("benchmarks/sim_episode.py", "--episodes", "1", "--steps", "2")
    assert "ratio fresh/held" in out and "ratio held/kept" in out and "ratio kept/cached" in out


@pytest.mark.sim
def test_ee_pose_prints_its_ratio_and_checks_the_joint_positions():
    out = run("benchmarks/ee_pose.py", "--steps", "5", "--rounds", "2")
    assert "round 2/2:" in out and "(same joint positions)" in out and "ratio scalar / ManiSkill's ee pose median" in out


def test_wm_train_threads_prints_its_ratio():
    out = run("benchmarks/wm_train_threads.py", "--steps", "1", "--repeats", "1")
    assert "1 thread(s):" in out and "2 thread(s):" in out and "ratio 1 thread(s) / 2" in out


@pytest.mark.sim
def test_rl_throughput_prints_every_round_and_the_median():
    out = run("benchmarks/rl_throughput.py", "--num-envs", "2", "--sim-envs", "1", "--wm-steps", "64",
              "--sim-steps", "8", "--rounds", "2", "--threads", "1")
    assert "round 1/2:" in out and "round 2/2:" in out
    assert "median of 2 round(s)" in out and "ratio world model / ManiSkill: median" in out


@pytest.mark.sim
def test_conv_layout_prints_both_layouts_and_the_ratio():
    out = run("benchmarks/conv_layout.py", "--num-envs", "2", "--steps", "32", "--goals", "2", "--rounds", "1",
              "--threads", "1")
    assert "default: decoder default, LPIPS default" in out and "timed: decoder " in out
    assert "round 1/1:" in out and "timed / default layouts median" in out
    bf16 = run("benchmarks/conv_layout.py", "--num-envs", "2", "--steps", "16", "--goals", "2", "--rounds", "1",
               "--threads", "1", "--wm-dtype", "bf16")
    assert "default: decoder channels_last, LPIPS channels_last (bf16)" in bf16 and "measures noise only" in bf16


@pytest.mark.sim
def test_kv_cache_prints_both_caches_the_ratio_and_that_they_agree():
    out = run("benchmarks/kv_cache.py", "--num-envs", "2", "--steps", "4", "--rounds", "2", "--threads", "1")
    assert "round 2/2 (bf16 first)" in out and "identical True" in out and "identical False" not in out
    assert "bf16 / fp32 KV cache median" in out


@pytest.mark.sim
def test_wave_threads_times_each_layout_against_the_first():
    out = run("benchmarks/wave_threads.py", "--steps", "8", "--num-envs", "1", "--rounds", "1",
              "--layouts", "1x1,2x1p")
    assert "round 1/1: 1 x 1 " in out and "2 x 1 passive" in out
    assert "1 x 1: " in out and "1.00x 1 x 1" in out and "x 1 passive: " in out
    bad = subprocess.run([sys.executable, "benchmarks/wave_threads.py", "--layouts", "2by2"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "'2by2' is not PxT" in bad.stderr
