"""The action world model as an RL environment: a batched stable-baselines3 ``VecEnv`` and a
single gymnasium ``Env`` on top of it.

reset: each env samples a training environment (task x scene) and one of its initial frames (and
the robot's proprioception there) from the collected data. step(action): the action is executed
as in the simulator (``stages.common.action_space``), the action WM predicts the next frame
(KV-cached, batched) and its proprioception head the robot's next state, the reward module scores
the frame, ``terminated`` = done head >= theta_done (for ``done_persist`` consecutive steps),
``truncated`` = step cap. A terminated step is
paid ``success_return`` (the module's maximum for this step and the steps left) when
``payout_gamma`` is set. With a ``guard`` (``stages.rl.guard``), the done-head ensemble's
disagreement is subtracted from every reward and a termination needs its confirmation. Observations come from ``ObservationFn`` (the same function the
simulator env uses).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from stages.common.action_space import executed
from stages.common.precision import autocast, conv_layout, resolved
from stages.common.proprio import PROPRIO_DIM
from stages.rl.rewards.base import RewardModule, StepBatch, success_return
from stages.sft.observation import ObservationFn, index_obs


@dataclass
class Start:
    """One initial state of one environment."""

    env_index: int  # row of the environment in the goals artifact
    instruction: str
    tokens: np.ndarray  # (h, w) the initial frame
    proprio: np.ndarray  # (10,) the robot's proprioception in it
    env: str = ""  # "<task>/<scene_id>", as the simulator env's info names it ("" where unknown)


def check_actions(actions: np.ndarray, n: int) -> np.ndarray:
    """(n, 7) finite float32 actions, or a ValueError that says what is wrong."""
    a = np.asarray(actions, dtype=np.float32)
    if a.shape != (n, 7):
        raise ValueError(f"expected actions of shape ({n}, 7), got {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        rows = sorted(set(np.nonzero(bad)[0].tolist()))
        raise ValueError(f"actions contain NaN or inf in envs {rows}: the world-model env only accepts finite actions")
    return a


class WorldModelVecEnv(VecEnv):
    """``num_envs`` world-model environments stepped as one batch."""

    render_mode = None

    def __init__(self, wm, tokenizer, obs_fn: ObservationFn, reward: RewardModule, starts: Sequence[Start], *,
                 num_envs: int, max_steps: int, theta_done: float, seed: int = 0, device: str = "cpu",
                 payout_gamma: float | None = None, guard=None, dtype: str = "fp32", done_persist: int = 1):
        if not starts:
            raise ValueError("the world-model env needs at least one initial state")
        action_space = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)
        super().__init__(num_envs, obs_fn.space, action_space)
        self.wm, self.tok, self.obs_fn, self.reward = wm, tokenizer, obs_fn, reward
        self.starts, self.max_steps, self.theta_done, self.device = list(starts), max_steps, theta_done, device
        self.payout_gamma, self.guard = payout_gamma, guard  # guard: stages.rl.guard.Guard or None
        if done_persist < 1:
            raise ValueError(f"done_persist must be >= 1, got {done_persist}")
        self.done_persist = done_persist
        # the world model's step and the decoding of its frames run in this precision ("fp32" | "bf16");
        # the proprioception head and the observations stay fp32, the reward module keeps its own
        # (the rl stage gives the LPIPS distance the same wm_dtype)
        self.dtype = resolved(device, dtype)
        self.rng = np.random.default_rng(seed)
        self.current: list[Start] = [self.starts[0]] * num_envs
        if reward.needs_frames:  # on a CPU, the decoder in the layout it runs faster in here (timed on a batch of frames)
            probe = torch.as_tensor(np.stack([s.tokens for s in self.current]).astype(np.int64), device=device)
            conv_layout(tokenizer.net.decoder, device, self.dtype, probe=lambda: self._decode(probe))
        # under bf16 autocast the cached attention reads keys and values in bf16: keep them so (identical results)
        self.roll = wm.rollout(num_envs, seed=seed, cache_dtype=torch.bfloat16 if self.dtype == "bf16" else torch.float32)
        self.t = np.zeros(num_envs, dtype=np.int64)
        self.held = np.zeros(num_envs, dtype=np.int64)  # (B,) consecutive steps the success has held so far
        self.proprio = torch.zeros(num_envs, PROPRIO_DIM, device=device)  # (B, 10) each env's robot state
        self._actions: np.ndarray | None = None
        self.stats = {"steps": 0, "episodes": 0, "terminated": 0, "truncated": 0}

    # ---- helpers ----------------------------------------------------------------------------------
    def _sample_starts(self, rows: np.ndarray) -> None:
        for r in rows:
            self.current[r] = self.starts[int(self.rng.integers(len(self.starts)))]
        self.t[rows] = 0
        self.held[rows] = 0

    def _batch(self, tokens: torch.Tensor, done: torch.Tensor, hidden: torch.Tensor,
               rows: np.ndarray | None = None) -> StepBatch:
        """The step's batch of every env, or of ``rows`` only (tokens, done, hidden then hold just those rows)."""
        current = self.current if rows is None else [self.current[r] for r in rows]
        batch = StepBatch(tokens, done, hidden, np.array([s.env_index for s in current]))
        if self.reward.needs_frames:
            batch.third, batch.wrist = self._decode(tokens)
        return batch

    def _decode(self, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The frames (third, wrist), each (B, 3, S, S) float32 in [0, 1], of tokens (B, h, w)."""
        with autocast(self.device, self.dtype):
            third, wrist = self.tok.decode(tokens)
        return third.float(), wrist.float()

    def _obs(self, tokens: torch.Tensor) -> dict[str, np.ndarray]:
        first = np.stack([s.tokens for s in self.current])  # (B, h, w) each env's real first frame
        return self.obs_fn.from_tokens(tokens.cpu(), self.proprio.cpu().numpy(), [s.instruction for s in self.current],
                                       first=first)

    def _start_proprio(self, rows: np.ndarray) -> None:
        self.proprio[torch.as_tensor(rows)] = torch.as_tensor(
            np.stack([self.current[r].proprio for r in rows]), dtype=torch.float32, device=self.proprio.device)

    def _restart(self, rows: np.ndarray, tokens: torch.Tensor, done: torch.Tensor, hidden: torch.Tensor) -> torch.Tensor:
        """Put new initial frames into ``rows``; returns the updated frame tokens (B, h, w)."""
        self._sample_starts(rows)
        self._start_proprio(rows)
        new = torch.as_tensor(np.stack([self.current[r].tokens for r in rows]).astype(np.int64), device=self.device)
        self.roll.reset(new, env_ids=torch.as_tensor(rows))
        tokens = tokens.clone()
        idx = torch.as_tensor(rows)
        tokens[idx] = new
        # the reward module reads the restarted envs' first frames only: decode just those
        self.reward.reset(rows, self._batch(new, done[idx], hidden[idx], rows))
        return tokens

    # ---- VecEnv -------------------------------------------------------------------------------------
    def reset(self) -> dict[str, np.ndarray]:
        rows = np.arange(self.num_envs)
        self._sample_starts(rows)
        self._start_proprio(rows)
        tokens = torch.as_tensor(np.stack([s.tokens for s in self.current]).astype(np.int64), device=self.device)
        self.roll.reset(tokens)
        zeros = torch.zeros(self.num_envs)
        self.reward.reset(rows, self._batch(tokens, zeros, torch.zeros(self.num_envs, self.wm.spec.dim)))
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return self._obs(tokens)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = executed(check_actions(actions, self.num_envs))

    def step_wait(self):
        actions, self._actions = self._actions, None
        if actions is None:
            raise RuntimeError("step_wait() called before step_async()")
        act = torch.as_tensor(actions, device=self.device)
        with autocast(self.device, self.dtype):
            out = self.roll.step(act)
        out.done_prob, out.hidden = out.done_prob.float(), out.hidden.float()  # (B,), (B, D)
        if getattr(self.wm, "proprio_head", None) is not None:
            self.proprio = self.wm.next_proprio(self.proprio, act, out.tokens)
        batch = self._batch(out.tokens, out.done_prob, out.hidden)
        rewards = np.asarray(self.reward(batch), dtype=np.float32)
        self.t += 1
        done_prob = out.done_prob.cpu().numpy()
        terminated = done_prob >= self.theta_done
        disagreement = None
        if self.guard is not None:  # penalise disagreement; a success must be confirmed by the ensemble
            disagreement, confirmed = self.guard(out.hidden)
            rewards = (rewards - self.guard.coef * self.reward.max_step_reward * disagreement).astype(np.float32)
            terminated &= confirmed
        self.held = np.where(terminated, self.held + 1, 0)
        terminated = self.held >= self.done_persist  # done_persist 1: the first step at or above theta_done
        truncated = (self.t >= self.max_steps) & ~terminated
        if self.payout_gamma is not None and terminated.any():
            paid = success_return(self.reward.max_step_reward, self.max_steps - self.t, self.payout_gamma)
            rewards = np.where(terminated, paid, rewards).astype(np.float32)
        dones = terminated | truncated
        obs = self._obs(out.tokens)
        infos: list[dict[str, Any]] = [{"done_prob": float(done_prob[i]), "env_id": self.current[i].env_index,
                                        "env": self.current[i].env,
                                        "clipped_actions": self.roll.last_clip_count} for i in range(self.num_envs)]
        if disagreement is not None:
            for i in range(self.num_envs):
                infos[i]["guard_std"] = float(disagreement[i])
        self.stats["steps"] += self.num_envs
        rows = np.nonzero(dones)[0]
        if len(rows):
            for r in rows:
                infos[r]["terminal_observation"] = index_obs(obs, r)
                infos[r]["TimeLimit.truncated"] = bool(truncated[r])
                infos[r]["terminated_by_done_head"] = bool(terminated[r])
            self.stats["episodes"] += len(rows)
            self.stats["terminated"] += int(terminated.sum())
            self.stats["truncated"] += int(truncated.sum())
            tokens = self._restart(rows, out.tokens, out.done_prob, out.hidden)
            obs = self._obs(tokens)
        return obs, rewards, dones, infos

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices=None) -> list:
        return [getattr(self, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name: str, value, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *args, indices=None, **kwargs) -> list:
        raise AttributeError(f"the world-model VecEnv has no per-env method {method_name!r}")

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * len(self._indices(indices))

    def _indices(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)


class WorldModelEnv(gym.Env):
    """One world-model environment with the gymnasium API (a batch-of-one ``WorldModelVecEnv``)."""

    metadata = {"render_modes": []}

    def __init__(self, vec: WorldModelVecEnv):
        if vec.num_envs != 1:
            raise ValueError(f"WorldModelEnv wraps a VecEnv of one env, got {vec.num_envs}")
        self.vec = vec
        self.observation_space, self.action_space = vec.observation_space, vec.action_space

    def reset(self, *, seed: int | None = None, options=None):
        super().reset(seed=seed)
        if seed is not None:
            self.vec.rng = np.random.default_rng(seed)
        obs = self.vec.reset()
        return index_obs(obs, 0), {}

    def step(self, action):
        self.vec.step_async(np.asarray(action, dtype=np.float32)[None])
        # step_wait auto-resets; report the terminal observation, as gymnasium expects
        obs, rew, done, infos = self.vec.step_wait()
        info = infos[0]
        if done[0]:
            terminated = info["terminated_by_done_head"]
            return info["terminal_observation"], float(rew[0]), bool(terminated), bool(not terminated), info
        return index_obs(obs, 0), float(rew[0]), False, False, info
