"""The reward-module registry: ``rl.reward`` selects one of ``REWARDS``.

``wm``, ``embedding`` and ``proxy`` score world-model frames (``RewardModule``); ``rule`` is RL in
the simulator with the task's hand-written dense reward (``stages.rl.sim_env``).
"""
from stages.rl.rewards.base import RewardModule, StepBatch
from stages.rl.rewards.heads import EmbeddingHead, EmbeddingReward, ProxyCNN, ProxyReward
from stages.rl.rewards.wm import GoalDistance, WMReward

REWARDS = ("wm", "rule", "embedding", "proxy")

__all__ = ["REWARDS", "RewardModule", "StepBatch", "WMReward", "GoalDistance", "EmbeddingHead",
           "EmbeddingReward", "ProxyCNN", "ProxyReward"]
