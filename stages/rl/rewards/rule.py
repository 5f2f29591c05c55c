"""``rule``: RL in the simulator on the task's hand-written dense reward (``stages.collect.envs``,
normalised to [0, 1]; 1 exactly at success). In diagnostics and tests it reads the recorded reward."""
from __future__ import annotations

import numpy as np

from stages.common.sim_env import RULE_MAX_STEP_REWARD
from stages.rl.rewards.base import RewardModule, RewardParts, StepBatch


class RuleReward(RewardModule):
    name = "rule"
    env = "sim"
    max_step_reward = RULE_MAX_STEP_REWARD

    @classmethod
    def build(cls, parts: RewardParts, cfg, num_envs: int) -> "RuleReward":
        return cls()

    def __call__(self, batch: StepBatch) -> np.ndarray:
        if batch.rule_reward is None:
            raise ValueError("the rule reward comes from the simulator: this batch carries none (rule_reward is None)")
        return np.asarray(batch.rule_reward, dtype=np.float64)
