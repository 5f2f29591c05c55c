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


def test_frozen_actor_features_keep_sfts_weights_while_the_actor_head_and_critic_learn():
    torch.manual_seed(0)
    model = _model(value_warmup_updates=0, freeze_actor_features=True, kl_coef=1.0, self_imitation_batches=2)
    pol = model.policy
    parts = {"features": pol.pi_features_extractor, "actor_mlp": pol.mlp_extractor.policy_net,
             "critic_features": pol.vf_features_extractor}
    before = {k: torch.cat([p.detach().flatten() for p in m.parameters()]).clone() for k, m in parts.items()}
    model.learn(total_timesteps=32)
    after = {k: torch.cat([p.detach().flatten() for p in m.parameters()]) for k, m in parts.items()}
    assert model.updates_done == 2
    assert torch.equal(before["features"], after["features"])
    assert not torch.equal(before["actor_mlp"], after["actor_mlp"])
    assert not torch.equal(before["critic_features"], after["critic_features"])


def test_freezing_a_shared_extractor_is_a_clear_error():
    import pytest

    from stages.rl.ppo import freeze_actor_features

    shared = make_policy(_model().observation_space, policy_kwargs([0.0] * 7, [1.0] * 7, features_dim=32, net_arch=32, share_features=True))
    with pytest.raises(ValueError, match="separate actor and critic extractors"):
        freeze_actor_features(shared)


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


def test_self_imitation_keeps_only_successful_episodes_with_their_discounted_returns():
    from stages.rl.self_imitation import SelfImitation

    sil = SelfImitation(n_envs=2, gamma=0.5, capacity=100, batches=1, batch_size=4, seed=0)
    obs = {"x": np.arange(2, dtype=np.float32)[:, None]}  # (n_envs, 1)
    actions = np.zeros((2, 3), np.float32)
    # env 0 succeeds at its third step; env 1 is truncated at its third step (a failure)
    for t, (done, success) in enumerate([(False, False), (False, False), (True, False)]):
        sil.record(obs, actions, np.array([1.0, 1.0]), np.array([done, done]), np.array([done, False]))
    assert sil.size == 3 and sil.episodes == 1
    assert np.allclose(sil.returns[:3], [1.75, 1.5, 1.0])  # 1 + .5 + .25, 1 + .5, 1
    assert np.all(sil.obs["x"][:3] == 0)  # only env 0's steps
    assert all(p == [] for p in sil.pending)


def test_self_imitation_raises_the_probability_of_a_successful_action():
    from stages.rl.self_imitation import SelfImitation

    torch.manual_seed(0)
    model = _model(value_warmup_updates=0, self_imitation_batches=8)
    assert isinstance(model.self_imitation, SelfImitation)
    obs = model.env.reset()  # Dict observation, (2, ...) per key
    action = np.full((2, 7), 0.3, np.float32)
    obs_t = {k: torch.as_tensor(v) for k, v in obs.items()}

    def log_prob():
        with torch.no_grad():
            return model.policy.evaluate_actions(obs_t, torch.as_tensor(action))[1].mean().item()

    before = log_prob()
    model.self_imitation.record(obs, action, np.array([50.0, 50.0]), np.array([True, True]), np.array([True, True]))
    stats = model.self_imitation.update(model.policy, model.max_grad_norm, model.vf_coef)
    assert stats["positive_fraction"] == 1.0 and stats["episodes"] == 2
    assert log_prob() > before
    off = _model(value_warmup_updates=0, self_imitation_batches=0)
    assert off.self_imitation is None


def test_ppo_with_self_imitation_records_steps_through_its_callback():
    from stages.rl.self_imitation import SelfImitationRecorder

    torch.manual_seed(0)
    model = _model(value_warmup_updates=0, self_imitation_batches=2)
    model.learn(total_timesteps=32, callback=SelfImitationRecorder(model.self_imitation))
    # max_steps 6 and an untrained done head: every episode is truncated, a failure, so nothing is kept
    assert model.self_imitation.size == 0 and sum(len(p) for p in model.self_imitation.pending) > 0


def test_success_weighted_self_imitation_clones_successes_and_leaves_the_critic_alone():
    torch.manual_seed(0)
    model = _model(value_warmup_updates=0, self_imitation_batches=4, self_imitation_weight="success")
    obs = model.env.reset()
    action = np.full((2, 7), 0.3, np.float32)
    obs_t = {k: torch.as_tensor(v) for k, v in obs.items()}
    before = model.policy.evaluate_actions(obs_t, torch.as_tensor(action))[1].mean().item()
    a0, v0 = _actor_critic(model)
    # a return far below any value the critic predicts: the advantage weight would be 0, this one is not
    model.self_imitation.record(obs, action, np.array([-50.0, -50.0]), np.array([True, True]), np.array([True, True]))
    model.self_imitation.update(model.policy, model.max_grad_norm, model.vf_coef)
    a1, v1 = _actor_critic(model)
    assert torch.equal(v0, v1) and not torch.equal(a0, a1)
    assert model.policy.evaluate_actions(obs_t, torch.as_tensor(action))[1].mean().item() > before


def test_the_noise_scale_multiplies_sfts_action_std_and_leaves_the_mean_alone():
    torch.manual_seed(0)
    sft_std = _model().policy.log_std.detach().exp()
    torch.manual_seed(0)
    model = _model(noise_scale=0.25)
    assert torch.allclose(model.policy.log_std.detach().exp(), 0.25 * sft_std)
    torch.manual_seed(0)
    same = _model()
    obs = model.env.reset()
    obs_t, _ = model.policy.obs_to_tensor(obs)
    with torch.no_grad():
        assert torch.allclose(model.policy.get_distribution(obs_t).mode(), same.policy.get_distribution(obs_t).mode())
