"""The policy: a stable-baselines3 actor-critic over {tokenizer latent, instruction embedding},
behaviour-cloned on planner demonstrations (SFT), then trained with PPO.

Any policy that maps the observation dict to a (7,) delta-EE action in [-1, 1] plugs into the same
envs: ``act(policy, obs) -> actions`` is the only call evaluation makes (a VLA on a GPU would
implement it with its own image pipeline behind ``ObservationFn``).
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from stable_baselines3 import PPO
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor


class LatentExtractor(BaseFeaturesExtractor):
    """codes (B, bits, h, w) -> small CNN; instruction (B, 384) -> linear; concatenated features."""

    def __init__(self, observation_space: gym.spaces.Dict, features_dim: int = 256):
        super().__init__(observation_space, features_dim)
        bits, h, w = observation_space["codes"].shape
        self.cnn = nn.Sequential(
            nn.Conv2d(bits, 64, 3, padding=1), nn.GELU(),
            nn.Conv2d(64, 64, 3, stride=2, padding=1), nn.GELU(),
            nn.Flatten(),
        )
        cnn_out = 64 * ((h + 1) // 2) * ((w + 1) // 2)
        text = observation_space["instruction"].shape[0]
        self.text = nn.Sequential(nn.Linear(text, 64), nn.GELU())
        self.proj = nn.Sequential(nn.Linear(cnn_out + 64, features_dim), nn.GELU())

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.proj(torch.cat([self.cnn(obs["codes"]), self.text(obs["instruction"])], 1))  # (B, F)


def make_ppo(env, cfg, seed: int, device: str) -> PPO:
    """PPO with the latent policy; hyper-parameters from the rl config."""
    model = PPO(
        "MultiInputPolicy", env, n_steps=cfg.n_steps, batch_size=cfg.batch_size, n_epochs=cfg.n_epochs,
        learning_rate=cfg.learning_rate, gamma=cfg.gamma, gae_lambda=0.95, clip_range=cfg.clip_range,
        ent_coef=cfg.ent_coef, seed=seed, device=device, verbose=0,
        policy_kwargs=dict(features_extractor_class=LatentExtractor, net_arch=dict(pi=[256, 256], vf=[256, 256]),
                           log_std_init=cfg.log_std_init),
    )
    # a logger without outputs: SB3's default one creates an empty /tmp/SB3-<time> directory per learn()
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def sft(model: PPO, obs: dict[str, np.ndarray], actions: np.ndarray, *, epochs: int, lr: float,
        batch_size: int, seed: int, progress=None) -> list[float]:
    """Behaviour cloning: regress the policy's mean action on demonstration (obs, action) pairs.

    obs: {"codes": (M, bits, h, w), "instruction": (M, 384)}, actions (M, 7). Returns epoch losses.
    """
    policy = model.policy
    dev = policy.device
    gen = torch.Generator().manual_seed(seed)
    params = [p for n, p in policy.named_parameters() if not n.startswith(("value_net", "mlp_extractor.value_net", "log_std"))]
    opt = torch.optim.Adam(params, lr=lr)
    tensors = {k: torch.as_tensor(v, device=dev) for k, v in obs.items()}
    target = torch.as_tensor(actions, dtype=torch.float32, device=dev).clamp(-1, 1)
    losses = []
    policy.set_training_mode(True)
    for _ in range(epochs):
        perm = torch.randperm(len(target), generator=gen).to(dev)
        total = 0.0
        for i in range(0, len(target), batch_size):
            idx = perm[i : i + batch_size]
            mean = policy.get_distribution({k: v[idx] for k, v in tensors.items()}).distribution.mean
            loss = F.mse_loss(mean, target[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        losses.append(total / len(target))
        if progress is not None:
            progress.update(1)
    policy.set_training_mode(False)
    return losses


def act(model: PPO, obs: dict[str, np.ndarray], deterministic: bool = True) -> np.ndarray:
    """Actions (B, 7) in [-1, 1] for an observation batch."""
    actions, _ = model.predict(obs, deterministic=deterministic)
    return np.clip(np.asarray(actions, dtype=np.float32), -1.0, 1.0)


def flat_params(model: PPO) -> torch.Tensor:
    return torch.cat([p.detach().flatten().cpu() for p in model.policy.parameters()])
