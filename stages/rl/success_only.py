"""``rl.rule_terms: success``: PPO in the simulator paid for success alone.

The task's dense reward (``stages.collect.envs``) pays reaching, grasping and nearing the target at
every step, up to 0.8 of success's 1 per step; success (with ``success_payout``) earns 1 for its step
and each one left. This wrapper keeps only that: a step that does not succeed earns 0, so PPO's
advantage compares episodes that succeed with ones that do not, not episodes that reach with ones
that do not. With SFT succeeding in ~40% of training episodes the signal is not sparse.
"""
from __future__ import annotations

import gymnasium as gym


class SuccessOnly(gym.Wrapper):
    """Reward = the wrapped env's reward on a successful step (``info['success']``), else 0."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, (float(reward) if info["success"] else 0.0), terminated, truncated, info
