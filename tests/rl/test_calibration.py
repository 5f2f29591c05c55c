"""The calibration gate: which tasks PPO may train on in the world model."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.rl.calibration import TaskCalibration, calibrate, imagined_successes, real_rates
from stages.rl.imagined import closed_loop
from stages.sft.policy import make_policy, policy_kwargs
from tests.rl.tiny import obs_fn, starts_for, tiny_action_wm, tiny_tokenizer


@pytest.mark.parametrize("imagined, real, kept", [
    (0, 46, False),   # the model never shows a success the policy gets half the time (pick-and-place at HEAD)
    (5, 46, True),    # 0.42 imagined vs 0.48 real
    (12, 19, False),  # 1.0 imagined vs 0.2 real: successes that do not happen
    (0, 0, True),     # never solved, never imagined solved
    (1, 0, False),    # never solved, imagined solved
])
def test_a_task_is_kept_when_its_imagined_rate_is_within_the_band_of_its_real_rate(imagined, real, kept):
    assert TaskCalibration("pick_place", imagined, 12, real, 96).kept(0.5) is kept


def test_real_rates_count_play_episodes_per_task_and_name_a_task_never_played():
    play = [{"env_id": "push/s1", "success": True}, {"env_id": "push/s2", "success": False},
            {"env_id": "pull/s1", "success": True}, {"env_id": "pick_place/s1", "success": False}]
    assert real_rates(play, ["push", "pull"]) == {"push": (1, 2), "pull": (1, 1)}
    with pytest.raises(ValueError, match="move_to_aim"):
        real_rates(play, ["push", "move_to_aim"])


@pytest.fixture(scope="module")
def parts():
    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    fn = obs_fn(tok)
    torch.manual_seed(0)
    policy = make_policy(fn.space, policy_kwargs([0.0] * 7, [0.3] * 6 + [1.0], features_dim=32, net_arch=32))
    return wm, fn, policy, starts_for(tok, n=4)


def test_imagined_successes_are_where_the_done_head_reached_theta_in_the_closed_loop(parts):
    wm, fn, policy, starts = parts
    tokens = torch.as_tensor(np.stack([s.tokens for s in starts]))
    proprio = np.stack([s.proprio for s in starts])
    peak = np.zeros(len(starts))  # (N,) the done head's highest probability over the horizon
    for s in closed_loop(policy, wm, fn, tokens, proprio, [s.instruction for s in starts], 4):
        peak = np.maximum(peak, s.out.done_prob.float().cpu().numpy())
    theta = float(np.median(peak))
    done = imagined_successes(policy, wm, fn, starts, 4, theta, batch=3)  # two batches, the same rollouts
    assert done.tolist() == (peak >= theta).tolist() and 0 < done.sum() < len(starts)
    assert not imagined_successes(policy, wm, fn, starts, 4, float(peak.max()) + 1e-3).any()
    assert imagined_successes(policy, wm, fn, starts, 4, 1e-6, persist=4).all()  # held for the whole horizon
    assert not imagined_successes(policy, wm, fn, starts, 4, 1e-6, persist=5).any()  # longer than the horizon


def test_calibrate_rates_each_task_on_its_own_starts(parts):
    wm, fn, policy, starts = parts
    play = [{"env_id": "push/a", "success": True}, {"env_id": "pull/a", "success": False},
            {"env_id": "pull/b", "success": False}]
    table = calibrate(policy, wm, fn, {"push": starts[:3], "pull": starts[3:]}, play, steps=3, theta=1e-6,
                      per_task=2, seed=0)
    assert [(c.task, c.imagined, c.starts, c.real, c.played) for c in table] == [("push", 2, 2, 1, 1),
                                                                                  ("pull", 1, 1, 0, 2)]
    assert [c.kept(0.5) for c in table] == [True, False]  # theta ~0: every imagined episode "succeeds"


def test_gated_ppo_is_its_own_method_and_every_valid_config_has_a_table_label():
    import itertools

    from pydantic import ValidationError

    from stages.evaluate.writeup import METHODS
    from stages.rl import REWARDS, Config, method_of

    assert method_of("wm", "success", calibration_ratio=0.5) == "wm_gated"
    assert method_of("wm", "success", calibration_ratio=0.0) == "wm"  # the gate off: the same label as before
    methods = set()
    for reward, terms, algorithm, select, ratio, branch, ibc, persist in itertools.product(
            REWARDS, ("success", "dense"), ("ppo", "filtered_bc"), ("success", "random", "none"), (0.0, 0.5), (0, 10),
            (0, 2), (1, 3)):
        try:
            cfg = Config(reward=reward, rule_terms=terms, algorithm=algorithm, fbc_select=select, calibration_ratio=ratio,
                         branch_horizon=branch, imagined_bc_epochs=ibc, done_persist=persist)
        except ValidationError:
            continue
        methods.add(method_of(cfg.reward, cfg.rule_terms, cfg.algorithm, cfg.fbc_select, cfg.calibration_ratio,
                              cfg.branch_horizon, cfg.imagined_bc_epochs, cfg.done_persist))
    assert {"wm", "wm_gated", "embedding_gated", "proxy_gated", "rule", "rule_dense", "wm_fbc", "wm_fbc_none",
            "wm_gated_ibc", "wm_branched", "wm_branched_ibc", "wm_fbc_persist", "wm_gated_persist"} <= methods
    assert methods <= set(METHODS), sorted(methods - set(METHODS))  # evaluate and the sweep report label each one


def test_ppo_in_the_world_model_is_gated_and_anchored_unless_told_otherwise():
    from pydantic import ValidationError

    from stages.rl import WM_PPO_CALIBRATION_RATIO, WM_PPO_DEMO_BC_BATCHES, Config, method_of

    def knobs(**kw):
        cfg = Config(**kw)
        return cfg.calibration_ratio, cfg.demo_bc_batches

    on = (WM_PPO_CALIBRATION_RATIO, WM_PPO_DEMO_BC_BATCHES)
    assert on == (0.5, 8)
    assert knobs() == on and knobs(reward="embedding") == on and knobs(reward="proxy") == on
    assert knobs(reward="rule") == (0.0, 0)  # PPO in ManiSkill: no gate, no anchor
    assert knobs(algorithm="filtered_bc") == (0.0, 0)  # no PPO update to gate or anchor
    assert knobs(calibration_ratio=0.0) == (0.0, 8) and knobs(demo_bc_batches=0) == (0.5, 0)  # a set value wins
    assert knobs(reward="rule", demo_bc_batches=8) == (0.0, 8)
    assert method_of("wm", "success", calibration_ratio=Config().calibration_ratio) == "wm_gated"
    with pytest.raises(ValidationError, match="calibration_ratio=0.5 gates"):
        Config(reward="rule", calibration_ratio=0.5)
    dumped = Config(reward="proxy").model_dump(mode="json")  # what the stage key hashes: the values used
    assert dumped["calibration_ratio"] == 0.5 and dumped["demo_bc_batches"] == 8
    assert Config.model_validate(dumped) == Config(reward="proxy")
