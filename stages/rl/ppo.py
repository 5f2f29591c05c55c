"""PPO (stable-baselines3) that starts from the SFT policy: same network, same weights, same
per-dimension action noise (set by the sft stage from its held-out residuals)."""
from __future__ import annotations

from stable_baselines3 import PPO
from stable_baselines3.common.logger import Logger

from stages.sft.policy import LatentExtractor, TaskPolicy


def make_ppo(env, cfg, sft_policy: TaskPolicy, sft_info: dict, device: str) -> PPO:
    """PPO with the rl config's hyper-parameters whose policy is a copy of ``sft_policy``."""
    # no dropout in PPO: its updates run in training mode and its rollouts in eval mode, so a dropout
    # layer would make the probability ratio compare two different networks (SFT's weights are kept as they are)
    fe = {**sft_info["policy_kwargs"]["features_extractor_kwargs"], "dropout": 0.0}
    kwargs = {**sft_info["policy_kwargs"], "features_extractor_kwargs": fe, "features_extractor_class": LatentExtractor}
    model = PPO(TaskPolicy, env, n_steps=cfg.n_steps, batch_size=cfg.batch_size, n_epochs=cfg.n_epochs,
                learning_rate=cfg.learning_rate, gamma=cfg.gamma, gae_lambda=0.95, clip_range=cfg.clip_range,
                ent_coef=cfg.ent_coef, seed=cfg.seed, device=device, verbose=0, policy_kwargs=kwargs)
    model.policy.load_state_dict(sft_policy.state_dict())
    # a logger without outputs: SB3's default one creates an empty /tmp/SB3-<time> directory per learn()
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model
