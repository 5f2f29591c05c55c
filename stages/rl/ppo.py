"""PPO (stable-baselines3) that starts from the SFT policy and keeps what it learned.

Same network, same weights, same per-dimension action noise (the sft stage sets it from its
held-out residuals); the actor and the critic have separate feature extractors (``TaskPolicy``).
On top of SB3's PPO, seven guards, each set in the rl config (docs/rl.md):
  - value warm-up: the first ``value_warmup_updates`` updates train the critic only, on rollouts
    of the unchanged SFT policy, so the first policy gradients use a value function that fits it;
  - ``target_kl``: SB3's early stop of an update's epochs once the policy moved that far;
  - ``kl_coef``: after each update, a pass over the rollout minimising
    ``kl_coef * KL(pi_sft(.|s) || pi(.|s))``, a pull back towards the SFT policy;
  - ``critic_lr_scale``: the critic's learning rate is the actor's times this (one Adam, two
    parameter groups), so a small actor step size does not leave the value function unfitted;
  - ``self_imitation_batches``: after each update, that many steps of self-imitation on the
    policy's own successful episodes (``stages.rl.self_imitation``);
  - ``freeze_actor_features``: the actor's feature extractor keeps SFT's weights;
  - ``demo_bc_batches``: after each update, that many steps of behaviour cloning on the SFT
    demonstrations (``stages.rl.demo_bc``), an anchor on the states SFT learned from.
Reward normalisation (``normalize_reward``) is the environment's: SB3's ``VecNormalize``.
"""
from __future__ import annotations

import copy
import math

import torch
from stable_baselines3 import PPO
from stable_baselines3.common.logger import Logger

from stages.rl.self_imitation import SelfImitation
from stages.sft.policy import LatentExtractor, TaskPolicy

CRITIC_MODULES = ("vf_features_extractor", "mlp_extractor.value_net", "value_net")


def critic_parameters(policy: TaskPolicy) -> set[int]:
    """ids of the critic's parameters (its own extractor, MLP and head)."""
    ids = set()
    for name in CRITIC_MODULES:
        ids |= {id(p) for p in policy.get_submodule(name).parameters()}
    return ids


class SFTPPO(PPO):
    """PPO with a critic-only warm-up and a KL pull towards a frozen copy of the starting policy."""

    def __init__(self, *args, value_warmup_updates: int = 0, kl_coef: float = 0.0, critic_lr_scale: float = 1.0, **kwargs):
        super().__init__(*args, **kwargs)
        self.value_warmup_updates, self.kl_coef = value_warmup_updates, kl_coef
        if critic_lr_scale != 1.0:
            critic = critic_parameters(self.policy)
            params = list(self.policy.parameters())
            groups = [{"params": [p for p in params if id(p) not in critic], "lr_scale": 1.0},
                      {"params": [p for p in params if id(p) in critic], "lr_scale": critic_lr_scale}]
            self.policy.optimizer = self.policy.optimizer_class(groups, lr=self.lr_schedule(1),
                                                                **self.policy.optimizer_kwargs)
        self.updates_done = 0
        self.reference: TaskPolicy | None = None
        self.kl_history: list[float] = []
        self.curves = None  # stages.common.curves.Curves: update statistics per PPO update when set
        self.self_imitation = None  # stages.rl.self_imitation.SelfImitation, filled by its recorder callback
        self.demo_bc = None  # stages.rl.demo_bc.DemoBC: the demonstration anchor when set

    def keep_reference(self) -> None:
        """Freeze a copy of the current policy (call after loading the SFT weights)."""
        self.reference = copy.deepcopy(self.policy).eval()
        for p in self.reference.parameters():
            p.requires_grad_(False)

    def _update_learning_rate(self, optimizers) -> None:
        # SB3 sets one rate on every parameter group; here each group keeps its scale (critic_lr_scale)
        lr = self.lr_schedule(self._current_progress_remaining)
        self.logger.record("train/learning_rate", lr)
        for optimizer in optimizers if isinstance(optimizers, list) else [optimizers]:
            for group in optimizer.param_groups:
                group["lr"] = lr * group.get("lr_scale", 1.0)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "reference", "curves", "self_imitation", "demo_bc"]  # policy.zip: the fine-tuned policy

    def train(self) -> None:
        warm = self.updates_done < self.value_warmup_updates
        frozen = []
        if warm:
            critic = critic_parameters(self.policy)
            frozen = [p for p in self.policy.parameters() if id(p) not in critic and p.requires_grad]
            for p in frozen:
                p.requires_grad_(False)
        try:
            super().train()
        finally:
            for p in frozen:
                p.requires_grad_(True)
        if not warm and self.kl_coef > 0 and self.reference is not None:
            self.kl_history.append(self._pull_towards_reference())
        sil_stats = {}
        if not warm and self.self_imitation is not None:
            sil_stats = self.self_imitation.update(self.policy, self.max_grad_norm, self.vf_coef)
        bc_stats = {}
        if not warm and self.demo_bc is not None:
            bc_stats = self.demo_bc.update(self.policy, self.max_grad_norm)
        if self.curves is not None:
            for name in ("approx_kl", "clip_fraction", "value_loss", "policy_gradient_loss", "explained_variance", "std"):
                self.curves.scalar(f"ppo/{name}", self.logger.name_to_value.get(f"train/{name}"), self.num_timesteps)
            if self.kl_history and not warm:
                self.curves.scalar("ppo/kl_to_sft", self.kl_history[-1], self.num_timesteps)
            for name, value in sil_stats.items():
                self.curves.scalar(f"self_imitation/{name}", value, self.num_timesteps)
            if "loss" in bc_stats:
                self.curves.scalar("demo_bc/loss", bc_stats["loss"], self.num_timesteps)
        self.updates_done += 1

    def _pull_towards_reference(self) -> float:
        """One pass over the rollout buffer minimising kl_coef * KL(reference || policy); mean KL."""
        self.policy.set_training_mode(True)
        kls = []
        for data in self.rollout_buffer.get(self.batch_size):
            dist = self.policy.get_distribution(data.observations).distribution
            with torch.no_grad():
                ref = self.reference.get_distribution(data.observations).distribution
            kl = torch.distributions.kl_divergence(ref, dist).sum(-1).mean()
            self.policy.optimizer.zero_grad(set_to_none=True)
            (self.kl_coef * kl).backward()
            torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
            self.policy.optimizer.step()
            kls.append(float(kl.detach()))
        self.policy.set_training_mode(False)
        return sum(kls) / max(len(kls), 1)


def make_ppo(env, cfg, sft_policy: TaskPolicy, sft_info: dict, device: str) -> SFTPPO:
    """PPO with the rl config's hyper-parameters whose policy is a copy of ``sft_policy``."""
    # no dropout in PPO: its updates run in training mode and its rollouts in eval mode, so a dropout
    # layer would make the probability ratio compare two different networks (SFT's weights are kept as they are)
    fe = {**sft_info["policy_kwargs"]["features_extractor_kwargs"], "dropout": 0.0}
    kwargs = {**sft_info["policy_kwargs"], "features_extractor_kwargs": fe, "features_extractor_class": LatentExtractor}
    # a minibatch larger than the rollout is the whole rollout (SB3 would warn about the remainder)
    batch_size = min(cfg.batch_size, cfg.n_steps * env.num_envs)
    model = SFTPPO(TaskPolicy, env, n_steps=cfg.n_steps, batch_size=batch_size, n_epochs=cfg.n_epochs,
                   learning_rate=cfg.learning_rate, gamma=cfg.gamma, gae_lambda=0.95, clip_range=cfg.clip_range,
                   ent_coef=cfg.ent_coef, target_kl=cfg.target_kl, seed=cfg.seed, device=device, verbose=0,
                   policy_kwargs=kwargs, value_warmup_updates=cfg.value_warmup_updates, kl_coef=cfg.kl_coef,
                   critic_lr_scale=cfg.critic_lr_scale)
    if cfg.self_imitation_batches:
        model.self_imitation = SelfImitation(env.num_envs, cfg.gamma, cfg.self_imitation_capacity,
                                             cfg.self_imitation_batches, batch_size, cfg.seed,
                                             cfg.self_imitation_weight)
    model.policy.load_state_dict(sft_policy.state_dict())
    if cfg.noise_scale != 1.0:
        with torch.no_grad():
            model.policy.log_std.add_(math.log(cfg.noise_scale))  # (7,) per-dimension log std, SFT's scaled
    if cfg.freeze_actor_features:
        freeze_actor_features(model.policy)
    model.keep_reference()
    # a logger without outputs: SB3's default one creates an empty /tmp/SB3-<time> directory per learn()
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def freeze_actor_features(policy: TaskPolicy) -> None:
    """Keep the actor's feature extractor at its current (SFT) weights: no gradient reaches it in PPO's,
    the KL pull's or self-imitation's updates (Adam skips a parameter without one); the critic's
    extractor, the actor's MLP, action head and ``log_std`` still learn."""
    if policy.share_features_extractor:
        raise ValueError("rl.freeze_actor_features needs separate actor and critic extractors (the SFT policy "
                         "shares one, so freezing it would freeze the critic's features too)")
    for p in policy.pi_features_extractor.parameters():
        p.requires_grad_(False)


def normalized_rewards(env, cfg):
    """``env`` wrapped in SB3's VecNormalize for rewards only (observations are codes and embeddings)."""
    if not cfg.normalize_reward:
        return env
    from stable_baselines3.common.vec_env import VecNormalize

    return VecNormalize(env, norm_obs=False, norm_reward=True, gamma=cfg.gamma)
