"""The demonstration anchor: behaviour cloning on SFT's demonstrations after each PPO update."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from stages.rl.demo_bc import DemoBC
from stages.sft.policy import bc_loss
from tests.rl.test_ppo import _model


def _demos(model, n: int = 32, seed: int = 0) -> tuple[dict, np.ndarray]:
    """Observations the env produces and an arbitrary 'demonstrated' action for each, (n, 7)."""
    rng = np.random.default_rng(seed)
    obs = model.env.reset()  # one per env
    actions = rng.uniform(-0.05, 0.05, (len(obs["proprio"]), 7)).astype(np.float32)
    reps = n // len(actions)
    return {k: np.concatenate([v] * reps) for k, v in obs.items()}, np.concatenate([actions] * reps)


def _bc(model, obs, actions, weights) -> float:
    with torch.no_grad():
        loss, _ = bc_loss(model.policy, {k: torch.as_tensor(v) for k, v in obs.items()}, torch.as_tensor(actions), weights)
    return float(loss)


def test_the_anchor_pulls_the_policy_towards_the_demonstrations_and_leaves_critic_and_noise_alone():
    weights = torch.ones(7)
    _model()  # the first build in a process times bf16 matmuls on random tensors (stages.common.precision, cached)
    # and so draws from torch's generator: after it, both runs below draw the same noise
    runs = {}
    for anchored in (False, True):
        torch.manual_seed(0)
        model = _model(value_warmup_updates=0, learning_rate=1e-3)
        obs, actions = _demos(model)
        if anchored:
            model.demo_bc = DemoBC(obs, actions, weights.numpy(), batches=20, batch_size=16, coef=1.0, seed=0)
        model.learn(total_timesteps=16)  # one rollout (2 envs x 8 steps), one update, then the anchor's steps
        runs[anchored] = model
    plain, anchored = runs[False], runs[True]
    assert _bc(anchored, obs, actions, weights) < 0.5 * _bc(plain, obs, actions, weights)
    assert anchored.demo_bc.last_stats["pairs"] == 32 and np.isfinite(anchored.demo_bc.last_stats["loss"])
    critic = [n for n, _ in plain.policy.named_parameters() if n.startswith(("vf_features_extractor", "mlp_extractor.value_net", "value_net"))]
    same = dict(plain.policy.named_parameters())
    for name, p in anchored.policy.named_parameters():
        if name in critic or name == "log_std":
            assert torch.equal(p, same[name]), name


def test_the_anchor_waits_for_the_critic_warm_up():
    torch.manual_seed(0)
    model = _model(value_warmup_updates=1, learning_rate=1e-3)
    obs, actions = _demos(model)
    model.demo_bc = DemoBC(obs, actions, np.ones(7), batches=4, batch_size=16, coef=1.0, seed=0)
    model.learn(total_timesteps=16)
    assert model.demo_bc.last_stats == {}  # the only update was the warm-up


@pytest.mark.parametrize("reader", ["anchor", "filtered_bc"])
def test_an_sft_artifact_without_its_demonstration_recipe_is_a_clear_error(tmp_path, reader):
    from stages.rl.filtered_bc import demonstration_pairs

    (tmp_path / "split.json").write_text(json.dumps({"train": ["a"], "val": []}))
    with pytest.raises(ValueError, match="rerun sft"):
        if reader == "anchor":
            DemoBC.from_sft(tmp_path, {"frame_skip": 4}, None, None, None, batches=1, batch_size=4, coef=1.0, seed=0)
        else:
            demonstration_pairs(tmp_path, {"frame_skip": 4}, None, None, None)
