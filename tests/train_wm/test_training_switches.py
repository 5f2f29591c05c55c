"""Training switches of train_wm: context-noise augmentation (rate, context only, shape errors) and the done-head negatives."""
import pytest
import torch

from stages.train_wm.data import corrupt_context
from stages.train_wm.model import WMSpec, WorldModelNet
from stages.train_wm.train import losses

V, GRID = 32, (4, 4)


def test_zero_rate_is_identity_and_rate_bounds_hold():
    gen = torch.Generator().manual_seed(0)
    tokens = torch.randint(0, V, (64, 5, 16))
    assert corrupt_context(tokens, 0.0, V, gen) is tokens
    noisy = corrupt_context(tokens, 0.4, V, gen)
    assert noisy.shape == tokens.shape and int(noisy.min()) >= 0 and int(noisy.max()) < V
    changed = (noisy != tokens).float().mean((1, 2))  # (B,) per-clip fraction
    # per clip: rate ~ U[0, 0.4], a replaced token keeps its value with prob 1/V
    assert float(changed.max()) <= 0.4 + 0.12
    assert 0.1 < float(changed.mean()) < 0.3  # mean rate 0.2 x (1 - 1/V)
    assert float(changed.std()) > 0.05  # the rate differs between clips


def test_noise_changes_the_context_not_the_targets():
    torch.manual_seed(0)
    net = WorldModelNet(WMSpec(kind="action", vocab_size=V, grid=GRID, dim=32, depth=2, heads=2, window=6,
                               control_tokens=3))
    tokens = torch.randint(0, V, (3, 5, 16))  # (B, T+1, N)
    batch = {"tokens": tokens, "valid": torch.ones(3, 4), "actions": torch.randn(3, 4, 7), "done": torch.zeros(3, 4)}
    clean = losses(net, batch, torch.Generator().manual_seed(1), "bce")
    same = losses(net, batch, torch.Generator().manual_seed(1), "bce", context_noise=0.0)
    noisy = losses(net, batch, torch.Generator().manual_seed(1), "bce", context_noise=1.0)
    assert torch.equal(clean["ce"], same["ce"])
    assert not torch.allclose(clean["ce"], noisy["ce"])
    with pytest.raises(ValueError, match="context must be"):
        net(tokens, batch["actions"], torch.ones(3, 4, 16, dtype=torch.bool), context=tokens[:, :3])


def test_done_negatives_switch_selects_the_action_wm_episodes():
    from types import SimpleNamespace

    from stages.train_wm import training_episodes

    eps = [SimpleNamespace(kind=k) for k in ("optimal", "near_miss", "perturbed", "near_miss")]
    assert [e.kind for e in training_episodes(eps, "action", True)] == ["optimal", "near_miss", "perturbed", "near_miss"]
    assert [e.kind for e in training_episodes(eps, "action", False)] == ["optimal", "perturbed"]
    assert [e.kind for e in training_episodes(eps, "text", True)] == ["optimal", "perturbed"]


def test_self_context_mixes_in_own_predictions_after_the_first_frame():
    from stages.train_wm.data import mix_context
    from stages.train_wm.train import own_predictions

    gen = torch.Generator().manual_seed(0)
    context = torch.randint(0, V, (256, 4, 16))
    predicted = torch.randint(0, V, (256, 4, 16))
    assert mix_context(context, predicted, 0.0, gen) is context
    mixed = mix_context(context, predicted, 0.5, gen)
    assert torch.equal(mixed[:, 0], context[:, 0])  # the observed start frame stays
    from_pred = (mixed[:, 1:] == predicted[:, :-1]).all(-1)  # (B, T-1) frame j is the prediction of frame j
    from_real = (mixed[:, 1:] == context[:, 1:]).all(-1)
    assert bool((from_pred | from_real).all())
    assert 0.4 < float(from_pred.float().mean()) < 0.6
    assert torch.equal(mix_context(context, predicted, 1.0, gen)[:, 1:], predicted[:, :-1])

    torch.manual_seed(0)
    net = WorldModelNet(WMSpec(kind="action", vocab_size=V, grid=GRID, dim=32, depth=2, heads=2, window=6,
                               control_tokens=3))
    tokens = torch.randint(0, V, (3, 5, 16))  # (B, T+1, N)
    batch = {"tokens": tokens, "valid": torch.ones(3, 4), "actions": torch.randn(3, 4, 7), "done": torch.zeros(3, 4)}
    pred = own_predictions(net, tokens, batch["actions"], tokens[:, :-1])
    assert pred.shape == (3, 4, 16) and not pred.requires_grad
    clean = losses(net, batch, torch.Generator().manual_seed(1), "bce")
    own = losses(net, batch, torch.Generator().manual_seed(1), "bce", self_context=1.0)
    assert not torch.allclose(clean["ce"], own["ce"])
    own["ce"].backward()  # gradients flow through the pass that reads the mixed context
    assert net.logits.weight.grad is not None
