"""The policy: a stable-baselines3 actor-critic over {tokenizer latent, proprioception, instruction},
behaviour-cloned on demonstrations here (SFT), then fine-tuned with PPO by the rl stage.

Any policy that maps the observation dict to a (7,) delta-EE action plugs into the same envs:
``act(policy, obs) -> actions`` is the only call evaluation makes (a VLA on a GPU would implement it
with its own image pipeline behind ``ObservationFn``).

Actions are normalised per dimension inside the network: the action head predicts z and the policy
outputs ``loc + scale * z`` (``Affine``, fixed buffers fitted on the demonstrations), so the loss
weighs a 0.1-sized arm action as much as the +-1 gripper, and PPO's Gaussian noise (``log_std``) is
set per dimension in action units from SFT's held-out residuals.
"""
from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from stable_baselines3.common.policies import MultiInputActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from stages.common.action_space import GRIPPER, executed

POLICY_FILE = "sft_policy.pt"


class LatentExtractor(BaseFeaturesExtractor):
    """codes (B, bits, h, w) -> small CNN; proprio (B, 10) -> MLP; instruction (B, 384) -> linear; concatenated.

    ``use_proprio=False`` zeroes the proprioception input (the ablation without it; same network);
    ``dropout`` applies to the flattened image features (they overfit first: 2,048 of them per frame).
    """

    def __init__(self, observation_space: gym.spaces.Dict, features_dim: int = 256, use_proprio: bool = True,
                 dropout: float = 0.0, members: int = 1):
        super().__init__(observation_space, features_dim * members)
        self.use_proprio = use_proprio
        if members > 1:  # an ensemble: ``members`` independent extractors side by side (module docstring)
            self.members = nn.ModuleList(LatentExtractor(observation_space, features_dim, use_proprio, dropout)
                                         for _ in range(members))
            return
        bits, h, w = observation_space["codes"].shape
        self.cnn = nn.Sequential(
            nn.Conv2d(bits, 64, 3, padding=1), nn.GELU(),
            nn.Conv2d(64, 64, 3, stride=2, padding=1), nn.GELU(),
            nn.Flatten(), nn.Dropout(dropout),
        )
        cnn_out = 64 * ((h + 1) // 2) * ((w + 1) // 2)
        self.proprio = nn.Sequential(nn.Linear(observation_space["proprio"].shape[0], 64), nn.GELU())
        self.text = nn.Sequential(nn.Linear(observation_space["instruction"].shape[0], 64), nn.GELU())
        self.proj = nn.Sequential(nn.Linear(cnn_out + 128, features_dim), nn.GELU())

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        if hasattr(self, "members"):
            return torch.cat([m(obs) for m in self.members], 1)  # (B, members * F)
        proprio = obs["proprio"] if self.use_proprio else torch.zeros_like(obs["proprio"])
        parts = [self.cnn(obs["codes"]), self.proprio(proprio), self.text(obs["instruction"])]
        return self.proj(torch.cat(parts, 1))  # (B, F)


class MemberMlpExtractor(nn.Module):
    """``members`` of SB3's ``MlpExtractor`` side by side: member k's actor and critic MLPs read the k-th
    block of the features (B, members * F) and their latents are concatenated (B, members * width).
    ``policy_net`` and ``value_net`` are the members' MLPs in order (the names SB3's extractor uses, so
    the code that tells the critic's parameters from the actor's by name reads them the same way)."""

    def __init__(self, feature_dim: int, net_arch, activation_fn, members: int, device="auto"):
        super().__init__()
        from stable_baselines3.common.torch_layers import MlpExtractor

        if feature_dim % members:
            raise ValueError(f"{feature_dim} features do not split into {members} members")
        one = [MlpExtractor(feature_dim // members, net_arch, activation_fn, device) for _ in range(members)]
        self.policy_net = nn.ModuleList(m.policy_net for m in one)
        self.value_net = nn.ModuleList(m.value_net for m in one)
        self.latent_dim_pi = members * one[0].latent_dim_pi
        self.latent_dim_vf = members * one[0].latent_dim_vf

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        chunks = features.chunk(len(self.policy_net), dim=1)
        return torch.cat([net(c) for net, c in zip(self.policy_net, chunks)], 1)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        chunks = features.chunk(len(self.value_net), dim=1)
        return torch.cat([net(c) for net, c in zip(self.value_net, chunks)], 1)


class Affine(nn.Module):
    """z (B, 7) -> loc + scale * z, with fixed (non-trained) loc and scale."""

    def __init__(self, loc, scale):
        super().__init__()
        self.register_buffer("loc", torch.as_tensor(loc, dtype=torch.float32))
        self.register_buffer("scale", torch.as_tensor(scale, dtype=torch.float32))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.loc + self.scale * z


class TaskPolicy(MultiInputActorCriticPolicy):
    """SB3's multi-input actor-critic whose action head ends in ``Affine(action_loc, action_scale)``.

    :param action_loc: (7,) per-dimension action offset (demonstration mean).
    :param action_scale: (7,) per-dimension action scale (demonstration std, floored).
    Every other argument is ``MultiInputActorCriticPolicy``'s.
    """

    def __init__(self, *args, action_loc=(0.0,) * 7, action_scale=(1.0,) * 7, members: int = 1, **kwargs):
        self.action_loc, self.action_scale = [float(v) for v in action_loc], [float(v) for v in action_scale]
        self.members = int(members)
        super().__init__(*args, **kwargs)

    def _build_mlp_extractor(self) -> None:
        if self.members == 1:
            return super()._build_mlp_extractor()
        self.mlp_extractor = MemberMlpExtractor(self.features_dim, self.net_arch, self.activation_fn, self.members,
                                                self.device)

    def _build(self, lr_schedule) -> None:
        super()._build(lr_schedule)
        self.action_net = nn.Sequential(self.action_net, Affine(self.action_loc, self.action_scale))

    def _get_constructor_parameters(self) -> dict[str, Any]:
        # SB3 2.9's ActorCriticPolicy does not save share_features_extractor: loaded without it, a policy with
        # separate actor / critic extractors comes back with ONE shared extractor that load_state_dict fills
        # last with the critic's weights, so the actor silently runs on untrained features
        return {**super()._get_constructor_parameters(), "action_loc": self.action_loc, "action_scale": self.action_scale,
                "share_features_extractor": self.share_features_extractor, "members": self.members}

    def mean_action(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The Gaussian's mean (B, 7) in action units, through the actor only."""
        extractor = self.pi_features_extractor if not self.share_features_extractor else self.features_extractor
        features = extractor(obs)
        return self.action_net(self.mlp_extractor.forward_actor(features))

    def normalized(self, actions: torch.Tensor) -> torch.Tensor:
        """Actions (B, 7) in the head's units z = (a - loc) / scale."""
        affine = self.action_net[-1]
        return (actions - affine.loc) / affine.scale


def policy_kwargs(action_loc, action_scale, *, features_dim: int = 256, net_arch: int = 256,
                  share_features: bool = False, log_std_init: float = -1.0, use_proprio: bool = True,
                  dropout: float = 0.0, members: int = 1) -> dict:
    """The constructor arguments that define the network: SFT builds it with these and PPO reuses them
    (``members`` > 1: an ensemble network, ``assemble``)."""
    fe = {"features_dim": features_dim, "use_proprio": use_proprio, "dropout": dropout}
    if members > 1:
        fe["members"] = members
    return dict(features_extractor_class=LatentExtractor, features_extractor_kwargs=fe,
                net_arch=dict(pi=[net_arch, net_arch], vf=[net_arch, net_arch]), share_features_extractor=share_features,
                log_std_init=log_std_init, action_loc=[float(v) for v in action_loc],
                action_scale=[float(v) for v in action_scale], **({"members": members} if members > 1 else {}))


def member_seed(seed: int, k: int) -> int:
    """The batch-order seed of ensemble member ``k`` of a run seeded ``seed`` (member 0: ``seed`` itself)."""
    return seed if k == 0 else int(np.random.SeedSequence([seed, k]).generate_state(1)[0])


@torch.no_grad()
def assemble(members: list[TaskPolicy], observation_space: gym.spaces.Dict, kwargs: dict) -> TaskPolicy:
    """One ``TaskPolicy`` whose mean action is the mean of the ``members``' mean actions, exactly.

    ``kwargs``: ``policy_kwargs(..., members=len(members))``. Member k's extractors and MLPs become block k
    of the ensemble's (``LatentExtractor`` and ``MemberMlpExtractor`` with ``members``); a linear layer on
    the concatenated latents is the sum of per-block linear layers, so the action head (and the value
    head) take the members' weights side by side divided by their number and the mean of their biases.
    The members must share ``action_loc`` / ``action_scale`` (fitted on the same demonstrations).
    ``log_std`` is left for the caller (the sft stage sets it from the ensemble's held-out residuals).
    """
    k = len(members)
    if k < 2 or kwargs.get("members") != k:
        raise ValueError(f"assemble needs 2+ members and policy kwargs built with members={k}")
    ens = make_policy(observation_space, kwargs).to(members[0].device)
    extractors = (["features_extractor"] if ens.share_features_extractor
                  else ["pi_features_extractor", "vf_features_extractor"])
    for i, m in enumerate(members):
        if m.action_loc != ens.action_loc or m.action_scale != ens.action_scale:
            raise ValueError(f"member {i}'s action normalisation differs from the ensemble's")
        for name in extractors:
            getattr(ens, name).members[i].load_state_dict(getattr(m, name).state_dict())
        for net in ("policy_net", "value_net"):
            getattr(ens.mlp_extractor, net)[i].load_state_dict(getattr(m.mlp_extractor, net).state_dict())
    for head in ("action_net", "value_net"):
        layers = [getattr(m, head)[0] if head == "action_net" else getattr(m, head) for m in members]
        target = getattr(ens, head)[0] if head == "action_net" else getattr(ens, head)
        target.weight.copy_(torch.cat([layer.weight for layer in layers], 1) / k)  # (out, k * width)
        target.bias.copy_(torch.stack([layer.bias for layer in layers]).mean(0))
    return ens.eval()


def make_policy(observation_space: gym.spaces.Dict, kwargs: dict, lr: float = 1e-3) -> TaskPolicy:
    """A fresh ``TaskPolicy`` for ``observation_space`` and 7-d actions in [-1, 1]."""
    action_space = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)
    return TaskPolicy(observation_space, action_space, lambda _: lr, **kwargs)


def dim_weights(gripper_weight: float = 1.0, rotation_weight: float = 1.0) -> torch.Tensor:
    """(7,) loss weights: translation 1, rotation ``rotation_weight``, gripper ``gripper_weight``."""
    return torch.tensor([1.0, 1.0, 1.0, rotation_weight, rotation_weight, rotation_weight, gripper_weight])


def bc_loss(policy: TaskPolicy, obs: dict[str, torch.Tensor], target: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(weighted mean loss, per-dimension squared error (B, 7) in normalised units) of the policy mean vs targets."""
    err = (policy.normalized(policy.mean_action(obs)) - policy.normalized(target)) ** 2  # (B, 7)
    weights = weights.to(err.device)
    return (err * weights).sum(1).mean() / weights.sum(), err


def behaviour_clone(policy: TaskPolicy, train: tuple[dict, np.ndarray], val: tuple[dict, np.ndarray] | None, *,
                    epochs: int, lr: float, weight_decay: float, batch_size: int, patience: int, weights: torch.Tensor,
                    seed: int, keep: str = "best", progress=None) -> dict:
    """Regress the policy's mean action on (obs, action) pairs with AdamW and a cosine schedule;
    keep the weights of the best held-out epoch (early stopping after ``patience`` epochs without
    improvement); ``keep="last"`` keeps the final weights and never stops early (the held-out loss is
    still recorded). obs: {"codes": (M, bits, h, w), "proprio": (M, 10), "instruction": (M, 384)},
    actions (M, 7). Returns the loss history and the best epoch.
    """
    dev = policy.device
    gen = torch.Generator().manual_seed(seed)
    params = [p for n, p in policy.named_parameters()
              if not n.startswith(("value_net", "mlp_extractor.value_net", "vf_features_extractor", "log_std"))]
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay)
    steps_per_epoch = max(1, math.ceil(len(train[1]) / batch_size))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(1.0, s / (epochs * steps_per_epoch)))))
    x = {k: torch.as_tensor(v, device=dev) for k, v in train[0].items()}
    y = torch.as_tensor(train[1], dtype=torch.float32, device=dev)
    hist: dict = {"train": [], "val": [], "best_epoch": 0, "epochs_run": 0}
    best, best_state, waited = float("inf"), None, 0
    for epoch in range(epochs):
        policy.set_training_mode(True)
        perm = torch.randperm(len(y), generator=gen).to(dev)
        total = 0.0
        for i in range(0, len(y), batch_size):
            idx = perm[i: i + batch_size]
            loss, _ = bc_loss(policy, {k: v[idx] for k, v in x.items()}, y[idx], weights)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach()) * len(idx)
        hist["train"].append(total / len(y))
        hist["epochs_run"] = epoch + 1
        if progress is not None:
            progress.update(1)
        if val is None:
            continue
        v = evaluate_pairs(policy, val, weights)["loss"]
        hist["val"].append(v)
        if v < best:
            best, best_state, waited, hist["best_epoch"] = v, copy.deepcopy(policy.state_dict()), 0, epoch + 1
        else:
            waited += 1
            if waited >= patience and keep == "best":
                break
    if best_state is not None and keep == "best":
        policy.load_state_dict(best_state)
    policy.set_training_mode(False)
    return hist


@torch.no_grad()
def evaluate_pairs(policy: TaskPolicy, pairs: tuple[dict, np.ndarray], weights: torch.Tensor | None = None,
                   batch_size: int = 1024) -> dict:
    """Weighted loss, per-dimension R^2 and residual std (action units), gripper sign accuracy."""
    weights = dim_weights() if weights is None else weights
    policy.set_training_mode(False)
    obs, actions = pairs
    dev = policy.device
    means = []
    for i in range(0, len(actions), batch_size):
        means.append(policy.mean_action({k: torch.as_tensor(v[i: i + batch_size], device=dev) for k, v in obs.items()}).cpu())
    pred = torch.cat(means).numpy()  # (M, 7)
    target = np.asarray(actions, np.float32)
    resid = pred - target
    z = resid / np.asarray(policy.action_net[-1].scale.cpu())  # normalised residuals (M, 7)
    w = weights.numpy()
    loss = float(((z ** 2).mean(0) * w).sum() / w.sum())
    var = target.var(0)
    r2 = 1.0 - (resid ** 2).mean(0) / np.where(var > 0, var, np.nan)
    return {"loss": loss, "r2": [float(v) for v in r2], "residual_std": [float(v) for v in resid.std(0)],
            "gripper_sign_accuracy": float(np.mean(np.sign(pred[:, GRIPPER] + 1e-12) == np.sign(target[:, GRIPPER])))}


def act(policy, obs: dict[str, np.ndarray], deterministic: bool = True) -> np.ndarray:
    """Executed actions (B, 7) for an observation batch (``stages.common.action_space.executed``)."""
    actions, _ = policy.predict(obs, deterministic=deterministic)
    return executed(np.asarray(actions, dtype=np.float32))


def load_policy(path: str | Path, device: str = "cpu"):
    """A trained policy: the SFT policy file (``sft_policy.pt``) or a PPO model zip (its policy)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no policy at {path}")
    if path.suffix == ".zip":
        return _policy_from_zip(path, device)
    return TaskPolicy.load(str(path), device=device)


def _policy_from_zip(path: Path, device: str):
    """The policy of an SB3 model zip, its weights only.

    Not ``PPO.load``: that also restores the optimizer into a freshly built one-group Adam, which
    fails for the rl stage's two parameter groups (actor and critic rates, ``critic_lr_scale``), and
    evaluation needs no optimizer.
    """
    from stable_baselines3.common.save_util import load_from_zip_file

    data, params, _ = load_from_zip_file(str(path), device=device)
    if data is None or "policy" not in params:
        raise ValueError(f"{path} is not an SB3 model zip with a policy")
    policy = data["policy_class"](data["observation_space"], data["action_space"], lambda _: 0.0,
                                  **data.get("policy_kwargs", {}))
    policy.load_state_dict(params["policy"])
    return policy.to(device).eval()


def flat_params(policy) -> torch.Tensor:
    return torch.cat([p.detach().flatten().cpu() for p in policy.parameters()])
