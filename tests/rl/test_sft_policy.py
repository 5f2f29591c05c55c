"""The SFT policy: saved and loaded intact, normalised actions, the gripper executed by its sign."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from stages.common.action_space import executed
from stages.sft.policy import act, behaviour_clone, dim_weights, evaluate_pairs, load_policy, make_policy, policy_kwargs


def _space(grid=(16, 8), bits=6) -> gym.spaces.Dict:
    return gym.spaces.Dict({"codes": gym.spaces.Box(-1, 1, (bits, *grid), np.float32),
                            "proprio": gym.spaces.Box(-np.inf, np.inf, (10,), np.float32),
                            "instruction": gym.spaces.Box(-np.inf, np.inf, (384,), np.float32)})


def _batch(space, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"codes": np.sign(rng.normal(size=(n, *space["codes"].shape))).astype(np.float32),
            "proprio": rng.normal(size=(n, 10)).astype(np.float32),
            "instruction": rng.normal(size=(n, 384)).astype(np.float32)}


def test_saved_policy_loads_with_the_same_actor(tmp_path):
    """Separate actor / critic extractors survive save + load (SB3 alone would share them on load)."""
    space = _space()
    policy = make_policy(space, policy_kwargs([0.1] * 7, [0.5] * 7, share_features=False, dropout=0.3))
    with torch.no_grad():  # make the critic's extractor differ from the actor's, as after training
        for p in policy.vf_features_extractor.parameters():
            p.add_(1.0)
    policy.save(str(tmp_path / "p.pt"))
    loaded = load_policy(tmp_path / "p.pt")
    assert not loaded.share_features_extractor
    obs = _batch(space, 5)
    np.testing.assert_array_equal(act(policy, obs), act(loaded, obs))
    for k, v in policy.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k


def test_behaviour_cloning_fits_a_state_dependent_action_in_action_units():
    space = _space(grid=(4, 2), bits=4)
    obs = _batch(space, 512)
    arm = 0.05 * np.tanh(obs["proprio"][:, :6])  # small arm actions, as in the demonstrations
    grip = np.where(obs["proprio"][:, 6] > 0, 1.0, -1.0)[:, None]
    actions = np.concatenate([arm, grip], 1).astype(np.float32)
    policy = make_policy(space, policy_kwargs(actions.mean(0), actions.std(0), features_dim=64, net_arch=64))
    hist = behaviour_clone(policy, (obs, actions), None, epochs=60, lr=3e-3, weight_decay=0.0, batch_size=128,
                           patience=5, weights=dim_weights(), seed=0)
    assert hist["train"][-1] < 0.3 * hist["train"][0]
    m = evaluate_pairs(policy, (obs, actions))
    assert min(m["r2"][:6]) > 0.5 and m["gripper_sign_accuracy"] > 0.9  # normalisation: the 0.05 arm dims are learnt too


def test_the_gripper_is_a_decision_executed_by_its_sign():
    a = executed(np.array([[0.3, -2.0, 0.0, 0.0, 0.0, 0.0, 0.2], [0, 0, 0, 0, 0, 0, -0.01], [0, 0, 0, 0, 0, 0, 0.0]]))
    np.testing.assert_array_equal(a[:, 6], [1.0, -1.0, 1.0])
    assert a[0, 1] == -1.0 and a[0, 0] == np.float32(0.3)


def _members(space, n: int, loc=(0.1,) * 7, scale=(0.5,) * 7) -> list:
    out = []
    for k in range(n):
        torch.manual_seed(k)
        out.append(make_policy(space, policy_kwargs(loc, scale, features_dim=32, net_arch=16)).eval())
    return out


def test_an_assembled_ensemble_acts_on_its_members_mean_and_survives_save_and_load(tmp_path):
    """``sft.ensemble``: one network whose mean action and value are the members' means (to float error),
    saved and loaded like any policy, its actions executed as one policy's."""
    from stages.sft.policy import assemble

    space = _space()
    members = _members(space, 3)
    ens = assemble(members, space, policy_kwargs([0.1] * 7, [0.5] * 7, features_dim=32, net_arch=16, members=3))
    obs = {k: torch.as_tensor(v) for k, v in _batch(space, 9).items()}
    with torch.no_grad():
        mean = torch.stack([m.mean_action(obs) for m in members]).mean(0)  # (9, 7)
        value = torch.stack([m.predict_values(obs) for m in members]).mean(0)  # (9, 1)
        torch.testing.assert_close(ens.mean_action(obs), mean, atol=1e-6, rtol=0)
        torch.testing.assert_close(ens.predict_values(obs), value, atol=1e-6, rtol=0)
        assert not torch.allclose(members[0].mean_action(obs), mean, atol=1e-3)  # the members do differ
    ens.save(str(tmp_path / "e.pt"))
    loaded = load_policy(tmp_path / "e.pt")
    assert loaded.members == 3 and len(loaded.pi_features_extractor.members) == 3
    np.testing.assert_array_equal(act(ens, _batch(space, 4)), act(loaded, _batch(space, 4)))


def test_assembling_members_of_other_normalisations_or_a_wrong_count_is_refused():
    import pytest

    from stages.sft.policy import assemble

    space = _space()
    kwargs = policy_kwargs([0.1] * 7, [0.5] * 7, features_dim=32, net_arch=16, members=2)
    with pytest.raises(ValueError, match="normalisation"):
        assemble(_members(space, 1) + _members(space, 1, scale=(0.4,) * 7), space, kwargs)
    with pytest.raises(ValueError, match="members=3"):
        assemble(_members(space, 3), space, kwargs)
