"""The reward-module registry: ``rl.reward`` names one entry of ``REGISTRY``, the only list of names.

``wm``, ``embedding`` and ``proxy`` score world-model frames; ``rule`` is RL in the simulator with
the task's hand-written dense reward. Every module bounds its per-step reward
(``max_step_reward``), and a success that ends an episode is paid that bound for its step and the
steps left (``success_return``): finishing out-earns lingering next to the goal, in every module.
"""
from stages.rl.rewards.base import RewardModule, RewardParts, StepBatch, success_return
from stages.rl.rewards.heads import EmbeddingHead, EmbeddingReward, ProxyCNN, ProxyReward
from stages.rl.rewards.rule import RuleReward
from stages.rl.rewards.wm import GoalDistance, WMReward

REGISTRY: dict[str, type[RewardModule]] = {cls.name: cls for cls in (WMReward, RuleReward, EmbeddingReward, ProxyReward)}
REWARDS = tuple(REGISTRY)

__all__ = ["REGISTRY", "REWARDS", "RewardModule", "RewardParts", "StepBatch", "success_return", "WMReward",
           "RuleReward", "GoalDistance", "EmbeddingHead", "EmbeddingReward", "ProxyCNN", "ProxyReward"]
