"""``rule``: RL in the simulator on the task's hand-written dense reward (``stages.collect.envs``,
normalised to [0, 1]; 1 exactly at success, at most 0.8 before). In diagnostics and tests it reads the
recorded reward; with ``rl.rule_terms: success`` it keeps only the successful step's, as the training
env does (``stages.rl.success_only``)."""
from __future__ import annotations

import numpy as np

from stages.common.sim_env import RULE_MAX_STEP_REWARD
from stages.rl.rewards.base import RewardModule, RewardParts, StepBatch


class RuleReward(RewardModule):
    name = "rule"
    env = "sim"
    max_step_reward = RULE_MAX_STEP_REWARD

    def __init__(self, success_only: bool = False):
        self.success_only = success_only

    @classmethod
    def build(cls, parts: RewardParts, cfg, num_envs: int) -> "RuleReward":
        return cls(success_only=cfg.rule_terms == "success")

    def __call__(self, batch: StepBatch) -> np.ndarray:
        if batch.rule_reward is None:
            raise ValueError("the rule reward comes from the simulator: this batch carries none (rule_reward is None)")
        r = np.asarray(batch.rule_reward, dtype=np.float64)  # (B,)
        return np.where(r >= self.max_step_reward, r, 0.0) if self.success_only else r
