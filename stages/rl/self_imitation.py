"""Self-imitation on the policy's own successes (after Oh et al., 2018, "Self-Imitation Learning").

PPO's gradient at the small step size that keeps the SFT policy intact (docs/rl.md) barely moves
it in a CPU budget of ~300 episodes. Each successful training episode, though, is a demonstration
from a state the policy itself reached. ``SelfImitation`` keeps the (observation, action,
discounted return) of every step of the last successful episodes, where success is the
environment's own flag (the simulator's check for ``rule``, the done head in the world model),
and after each PPO update takes ``batches`` gradient steps on

    - log pi(a|s) * max(R - V(s), 0)  +  vf_coef/2 * max(R - V(s), 0)^2

over minibatches sampled from it (``weight: advantage``): the policy imitates a successful action
only where its return beat what the critic expected, and the critic learns that such returns are
possible. Returns are computed from the rewards PPO itself sees (after reward normalisation), so R
and V share a scale. With ``weight: success`` every stored step weighs 1 and the critic is left
alone (- log pi(a|s), behaviour cloning on the policy's own successes, which is reward-weighted
regression with a 0/1 reward). Failed episodes never enter the buffer.
"""
from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """R_t = sum_k gamma^k r_{t+k} to the episode's end: (T,) -> (T,)."""
    out = np.zeros(len(rewards), dtype=np.float32)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = float(rewards[t]) + gamma * running
        out[t] = running
    return out


class SelfImitation:
    """A ring buffer of successful episodes' steps and the self-imitation update on it."""

    def __init__(self, n_envs: int, gamma: float, capacity: int, batches: int, batch_size: int, seed: int,
                 weight: str = "advantage"):
        if weight not in ("advantage", "success"):
            raise ValueError(f"self-imitation weight {weight!r}: expected 'advantage' or 'success'")
        self.gamma, self.capacity, self.batches, self.batch_size = gamma, capacity, batches, batch_size
        self.weight = weight
        self.rng = np.random.default_rng(seed)
        self.pending: list[list[tuple[dict, np.ndarray, float]]] = [[] for _ in range(n_envs)]
        self.obs: dict[str, np.ndarray] | None = None  # key -> (capacity, *shape)
        self.actions: np.ndarray | None = None          # (capacity, action_dim)
        self.returns = np.zeros(capacity, dtype=np.float32)
        self.size = self.cursor = 0
        self.episodes = 0
        self.last_stats: dict[str, float] = {}

    # ---- filling ------------------------------------------------------------------------------------
    def record(self, obs: dict[str, np.ndarray], actions: np.ndarray, rewards: np.ndarray, dones: np.ndarray,
               successes: np.ndarray) -> None:
        """One vectorised step: obs (n_envs, ...) the step was taken from, actions (n_envs, A), rewards (n_envs,)."""
        for i in range(len(actions)):
            self.pending[i].append(({k: np.array(v[i]) for k, v in obs.items()}, np.array(actions[i]), float(rewards[i])))
            if dones[i]:
                if successes[i]:
                    self._store(self.pending[i])
                self.pending[i] = []

    def _store(self, steps: list[tuple[dict, np.ndarray, float]]) -> None:
        steps = steps[-self.capacity:]
        returns = discounted_returns(np.array([r for _, _, r in steps]), self.gamma)  # (T,)
        if self.obs is None:
            self.obs = {k: np.zeros((self.capacity, *v.shape), dtype=v.dtype) for k, v in steps[0][0].items()}
            self.actions = np.zeros((self.capacity, *steps[0][1].shape), dtype=np.float32)
        for (o, a, _), ret in zip(steps, returns):
            for k, v in o.items():
                self.obs[k][self.cursor] = v
            self.actions[self.cursor] = a
            self.returns[self.cursor] = ret
            self.cursor = (self.cursor + 1) % self.capacity
            self.size = min(self.size + 1, self.capacity)
        self.episodes += 1

    # ---- learning -----------------------------------------------------------------------------------
    def update(self, policy, max_grad_norm: float, vf_coef: float) -> dict[str, float]:
        """``batches`` gradient steps of the self-imitation loss through the policy's optimizer."""
        if self.size == 0 or self.batches == 0:
            return {}
        device = policy.device
        policy.set_training_mode(True)
        weights, gaps = [], []
        for _ in range(self.batches):
            idx = self.rng.integers(0, self.size, min(self.batch_size, self.size))
            obs = {k: torch.as_tensor(v[idx], device=device) for k, v in self.obs.items()}
            actions = torch.as_tensor(self.actions[idx], device=device)      # (B, A)
            returns = torch.as_tensor(self.returns[idx], device=device)      # (B,)
            values, log_prob, _ = policy.evaluate_actions(obs, actions)      # (B, 1), (B,)
            gap = (returns - values.flatten()).clamp(min=0.0)                # (B,)
            if self.weight == "advantage":
                loss = -(log_prob * gap.detach()).mean() + 0.5 * vf_coef * gap.pow(2).mean()
            else:
                loss = -log_prob.mean()
            policy.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), max_grad_norm)
            policy.optimizer.step()
            weights.append(float((gap > 0).float().mean()))
            gaps.append(float(gap.detach().mean()))
        policy.set_training_mode(False)
        self.last_stats = {"buffer_steps": float(self.size), "episodes": float(self.episodes),
                           "positive_fraction": float(np.mean(weights)), "mean_gap": float(np.mean(gaps))}
        return self.last_stats


class SelfImitationRecorder(BaseCallback):
    """Feeds every PPO environment step to a ``SelfImitation`` buffer (the rewards PPO sees)."""

    def __init__(self, sil: SelfImitation):
        super().__init__()
        self.sil = sil

    def _on_step(self) -> bool:
        obs = {k: v.cpu().numpy() for k, v in self.locals["obs_tensor"].items()}  # the step's Dict observation
        dones, infos = self.locals["dones"], self.locals["infos"]
        successes = np.array([bool(info.get("success", info.get("terminated_by_done_head", False))) for info in infos])
        self.sil.record(obs, self.locals["actions"], self.locals["rewards"], dones, successes)
        return True
