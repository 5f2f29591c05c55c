"""PPO from the SFT policy: the critic-only warm-up and the KL pull towards the SFT policy."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from stages.rl import Config
from stages.rl.ppo import critic_parameters, make_ppo
from stages.rl.rewards import GoalDistance, WMReward
from stages.rl.wm_env import WorldModelVecEnv
from stages.sft.policy import make_policy, policy_kwargs
from tests.rl.tiny import obs_fn, starts_for, tiny_action_wm, tiny_tokenizer


def _model(**overrides):
    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    g3, gw = tok.decode(torch.as_tensor(np.stack([s.tokens for s in starts_for(tok)[:2]]).astype(np.int64)))
    env = WorldModelVecEnv(wm, tok, obs_fn(tok), WMReward(GoalDistance(g3, gw), alpha=1.0, beta=0.01, theta_sps=0.5,
                                                          num_envs=2),
                           starts_for(tok), num_envs=2, max_steps=6, theta_done=0.999, seed=0)
    kwargs = policy_kwargs([0.0] * 7, [0.1] * 6 + [1.0], features_dim=32, net_arch=32)
    sft = make_policy(env.observation_space, kwargs)
    info = {"policy_kwargs": {k: v for k, v in kwargs.items() if k != "features_extractor_class"}}
    cfg = SimpleNamespace(**{**Config().model_dump(), "n_steps": 8, "batch_size": 16, "n_epochs": 2,
                             "target_kl": None, **overrides})
    return make_ppo(env, cfg, sft, info, "cpu")


def _actor_critic(model):
    critic = critic_parameters(model.policy)
    actor = torch.cat([p.detach().flatten() for p in model.policy.parameters() if id(p) not in critic])
    value = torch.cat([p.detach().flatten() for p in model.policy.parameters() if id(p) in critic])
    return actor.clone(), value.clone()


def test_the_warm_up_trains_the_critic_only_then_the_actor_learns():
    torch.manual_seed(0)
    model = _model(value_warmup_updates=1)
    a0, v0 = _actor_critic(model)
    model.learn(total_timesteps=16)  # one rollout, one (warm-up) update
    a1, v1 = _actor_critic(model)
    assert model.updates_done == 1 and torch.equal(a0, a1) and not torch.equal(v0, v1)
    assert all(p.requires_grad for p in model.policy.parameters())  # unfrozen after the warm-up
    model.learn(total_timesteps=16, reset_num_timesteps=False)
    a2, _ = _actor_critic(model)
    assert model.updates_done == 2 and not torch.equal(a1, a2)


def test_the_kl_pull_runs_after_each_policy_update_against_the_frozen_sft_copy():
    torch.manual_seed(0)
    model = _model(value_warmup_updates=0, kl_coef=1.0)
    ref = [p.detach().clone() for p in model.reference.parameters()]
    model.learn(total_timesteps=32)
    assert len(model.kl_history) == 2 and all(np.isfinite(model.kl_history))
    assert all(torch.equal(a, b) for a, b in zip(ref, model.reference.parameters()))  # the reference never moves


def test_the_critic_learning_rate_is_scaled_and_survives_sb3s_schedule():
    torch.manual_seed(0)
    model = _model(value_warmup_updates=0, learning_rate=1e-5, critic_lr_scale=10.0)
    model.learn(total_timesteps=16)  # SB3 resets the optimizer's rates before every update
    critic = critic_parameters(model.policy)
    rates = {("critic" if id(g["params"][0]) in critic else "actor"): g["lr"] for g in model.policy.optimizer.param_groups}
    assert rates == {"actor": 1e-5, "critic": 1e-4}
    assert sum(len(g["params"]) for g in model.policy.optimizer.param_groups) == len(list(model.policy.parameters()))
    plain = _model(value_warmup_updates=0, learning_rate=1e-5, critic_lr_scale=1.0)
    plain.learn(total_timesteps=16)
    assert [g["lr"] for g in plain.policy.optimizer.param_groups] == [1e-5]


def test_a_ppo_zip_with_two_learning_rates_loads_for_evaluation(tmp_path):
    from stages.sft.policy import flat_params, load_policy

    torch.manual_seed(0)
    model = _model(value_warmup_updates=0, critic_lr_scale=10.0)
    model.learn(total_timesteps=16)
    model.save(tmp_path / "policy.zip")
    loaded = load_policy(tmp_path / "policy.zip")
    assert torch.equal(flat_params(loaded), flat_params(model.policy))
    assert not loaded.training
    obs = model.env.reset()
    a0, _ = model.policy.predict(obs, deterministic=True)
    a1, _ = loaded.predict(obs, deterministic=True)
    assert np.allclose(a0, a1)
