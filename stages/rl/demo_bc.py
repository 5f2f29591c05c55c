"""Behaviour cloning on the SFT demonstrations during PPO: an anchor on the states SFT learned from.

After Rajeswaran et al. (2018, "Learning Complex Dexterous Manipulation with Deep Reinforcement
Learning and Demonstrations", DAPG), who add the demonstrations' log-likelihood to the policy
gradient. ``rl.kl_coef`` pulls the policy towards SFT on the states PPO visits; this pulls it
towards the demonstrated actions on the demonstrations' own states, the data SFT was fitted to, so
what PPO and self-imitation change elsewhere does not unlearn them. After each PPO update (never
during the critic-only warm-up) it takes ``batches`` gradient steps on

    coef * sum_d w_d * (mean_d(s) - a_d)^2 / sum_d w_d      (normalised action units)

over minibatches of the SFT stage's training pairs: the sft stage's own loss (``bc_loss``) with its
per-dimension weights, on the demonstrations it trained on, read the way it read them (both from
its ``policy.json``). The loss is on the mean only, so PPO's action noise is left to PPO.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from stages.rl.demonstrations import sft_pairs
from stages.sft.policy import bc_loss


class DemoBC:
    """The SFT training pairs and the anchoring update on them."""

    def __init__(self, obs: dict[str, np.ndarray], actions: np.ndarray, weights: np.ndarray, *, batches: int,
                 batch_size: int, coef: float, seed: int):
        if len(actions) == 0:
            raise ValueError("demonstration anchor: no demonstration pairs")
        self.obs, self.actions = obs, actions.astype(np.float32)  # key -> (M, ...), (M, 7)
        self.weights = torch.as_tensor(np.asarray(weights, dtype=np.float32))  # (7,)
        self.batches, self.batch_size, self.coef = batches, batch_size, coef
        self.rng = np.random.default_rng(seed)
        self.last_stats: dict[str, float] = {}

    @classmethod
    def from_sft(cls, sft_dir: Path, sft_info: dict, dataset, store, obs_fn, *, batches: int, batch_size: int,
                 coef: float, seed: int) -> "DemoBC":
        """The training demonstrations of the sft artifact at ``sft_dir``, read with its recipe."""
        train = sft_pairs(sft_dir, sft_info, dataset, store, obs_fn, "train")
        if train is None:
            raise ValueError(f"demonstration anchor: {sft_dir}/split.json lists no training demonstrations")
        obs, actions = train
        return cls(obs, actions, np.asarray(sft_info["demonstrations"]["loss_weights"]), batches=batches,
                   batch_size=batch_size, coef=coef, seed=seed)

    def __len__(self) -> int:
        return len(self.actions)

    def update(self, policy, max_grad_norm: float) -> dict[str, float]:
        """``batches`` gradient steps of ``coef * bc_loss`` through the policy's optimizer; mean loss."""
        if self.batches == 0:
            return {}
        device = policy.device
        policy.set_training_mode(True)
        losses = []
        for _ in range(self.batches):
            idx = self.rng.integers(0, len(self.actions), min(self.batch_size, len(self.actions)))
            obs = {k: torch.as_tensor(v[idx], device=device) for k, v in self.obs.items()}
            target = torch.as_tensor(self.actions[idx], device=device)  # (B, 7)
            loss, _ = bc_loss(policy, obs, target, self.weights)
            policy.optimizer.zero_grad(set_to_none=True)
            (self.coef * loss).backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), max_grad_norm)
            policy.optimizer.step()
            losses.append(float(loss.detach()))
        policy.set_training_mode(False)
        self.last_stats = {"loss": float(np.mean(losses)), "pairs": float(len(self.actions))}
        return self.last_stats
