"""World-model network and rollout: conditioning, exact KV cache, save/load, action checks, learning."""
import numpy as np
import pytest
import torch

from stages.train_wm.data import ClipSampler, Episode
from stages.train_wm.model import WMSpec, WorldModelNet
from stages.train_wm.rollout import WorldModel, load_net, save_world_model
from stages.train_wm.train import train_world_model

V, GRID = 32, (4, 4)


def make_net(kind: str, window: int = 6, seed: int = 0) -> WorldModelNet:
    torch.manual_seed(seed)
    net = WorldModelNet(WMSpec(kind=kind, vocab_size=V, grid=GRID, dim=32, depth=2, heads=2, window=window,
                               control_tokens=3))
    for p in net.parameters():  # untrained weights of a realistic scale, so outputs are not all ~equal
        if p.dim() >= 2:
            torch.nn.init.normal_(p, std=0.3)
    net.set_action_stats(torch.randn(100, 7))
    return net.eval()


def control_for(kind: str, b: int, t: int) -> torch.Tensor:
    return torch.randn(b, t, 7) * 0.5 if kind == "action" else torch.randn(b, 384)


@pytest.mark.parametrize("kind", ["action", "text"])
def test_conditioning_changes_logits_and_every_dim_gets_gradient(kind):
    net = make_net(kind)
    b, t, n = 2, 3, GRID[0] * GRID[1]
    tokens = torch.randint(0, V, (b, t + 1, n))
    mask = torch.ones(b, t, n, dtype=torch.bool)
    control = control_for(kind, b, t).requires_grad_(True)
    logits, done = net(tokens, control, mask)
    other = control.detach() + torch.randn_like(control)
    logits2, _ = net(tokens, other, mask)
    assert (logits - logits2).abs().max() > 1e-3
    (logits.square().sum() + done.square().sum()).backward()
    per_dim = control.grad.abs().flatten(0, -2).sum(0) if kind == "action" else control.grad.abs().sum(0)
    assert per_dim.shape == ((7,) if kind == "action" else (384,))
    assert (per_dim > 0).all(), f"dims without gradient: {(per_dim == 0).nonzero().flatten().tolist()}"


def test_action_changes_each_step_prediction():
    wm = WorldModel(make_net("action"), decode_steps=1)
    roll = wm.rollout(2)
    tokens0 = torch.randint(0, V, (1, *GRID)).expand(2, *GRID)
    roll.reset(tokens0)
    a = torch.zeros(2, 7)
    a[1] = wm.net.action_high
    out = roll.step(a)
    assert (out.hidden[0] - out.hidden[1]).abs().max() > 1e-4


@pytest.mark.parametrize("kind", ["action", "text"])
def test_kv_cached_rollout_equals_full_forward(kind):
    net = make_net(kind, window=6)
    b, t, n = 3, 6, GRID[0] * GRID[1]
    tokens = torch.randint(0, V, (b, t + 1, n))
    control = control_for(kind, b, t)
    with torch.no_grad():
        _, done_full = net(tokens, control, torch.zeros(b, t, n, dtype=torch.bool))
        logits_full, _ = net(tokens, control, torch.ones(b, t, n, dtype=torch.bool))
    wm = WorldModel(net, decode_steps=1)
    done_cached = wm.done_for_sequences(tokens.view(b, t + 1, *GRID), control)
    assert torch.allclose(done_cached, torch.sigmoid(done_full), atol=1e-5)
    # one-pass greedy decoding of each next frame from the true history equals argmax of the full pass
    roll = wm.rollout(b)
    roll.reset(tokens[:, 0].view(b, *GRID), None if kind == "action" else control)
    for i in range(t):
        pred = roll.step(control[:, i] if kind == "action" else None).tokens.view(b, n)
        assert torch.equal(pred, logits_full[:, i].argmax(-1))
        roll.frame = tokens[:, i + 1].clone()  # continue from the true frame (teacher forcing)


def test_sliding_window_and_partial_reset():
    net = make_net("action", window=4)
    wm = WorldModel(net, decode_steps=2)
    b, t = 3, 9
    tokens = torch.randint(0, V, (b, t + 1, *GRID))
    acts = torch.randn(b, t, 7) * 0.5
    done = wm.done_for_sequences(tokens, acts)  # runs past the window without error
    assert done.shape == (b, t) and torch.isfinite(done).all()
    # an env restarted mid-rollout behaves exactly like a fresh rollout
    fresh = wm.rollout(b)
    fresh.reset(tokens[:, 0])
    ref = [fresh.step(acts[:, i], next_tokens=tokens[:, i + 1]).hidden for i in range(6)]
    roll = wm.rollout(b)
    roll.reset(tokens[:, 0])
    for i in range(5):
        roll.step(torch.randn(b, 7), next_tokens=torch.randint(0, V, (b, *GRID)))
    roll.reset(tokens[1:2, 0], env_ids=torch.tensor([1]))
    for i in range(6):
        a = torch.randn(b, 7)
        a[1] = acts[1, i]
        nt = torch.randint(0, V, (b, *GRID))
        nt[1] = tokens[1, i + 1]
        h = roll.step(a, next_tokens=nt).hidden
        assert torch.allclose(h[1], ref[i][1], atol=1e-5), i


def test_save_load_round_trip(tmp_path):
    net = make_net("action")
    save_world_model(net, tmp_path / "wm.pt")
    net2 = load_net(tmp_path / "wm.pt")
    assert net2.spec == net.spec
    for k, v in net.state_dict().items():
        assert torch.equal(v, net2.state_dict()[k]), k
    tokens = torch.randint(0, V, (2, *GRID))
    outs = []
    for n in (net, net2):
        roll = WorldModel(n, decode_steps=2).rollout(2)
        roll.reset(tokens)
        outs.append(roll.step(torch.randn(2, 7, generator=torch.Generator().manual_seed(1))))
    assert torch.equal(outs[0].tokens, outs[1].tokens) and torch.allclose(outs[0].done_prob, outs[1].done_prob)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_actions_raise(bad):
    roll = WorldModel(make_net("action")).rollout(2)
    roll.reset(torch.zeros(2, *GRID, dtype=torch.long))
    a = torch.zeros(2, 7)
    a[1, 3] = bad
    with pytest.raises(ValueError, match="NaN or inf"):
        roll.step(a)


def test_user_errors_are_clear():
    roll = WorldModel(make_net("action")).rollout(2)
    with pytest.raises(RuntimeError, match="reset"):
        roll.step(torch.zeros(2, 7))
    with pytest.raises(ValueError, match="shape"):
        roll.reset(torch.zeros(3, *GRID, dtype=torch.long))
    with pytest.raises(ValueError, match=r"\[0, 32\)"):
        roll.reset(torch.full((2, *GRID), V))
    roll.reset(torch.zeros(2, *GRID, dtype=torch.long))
    with pytest.raises(ValueError, match="shape"):
        roll.step(torch.zeros(2, 6))
    text = WorldModel(make_net("text")).rollout(2)
    with pytest.raises(ValueError, match="instruction embeddings"):
        text.reset(torch.zeros(2, *GRID, dtype=torch.long))


def test_clipping_is_counted():
    net = make_net("action")
    roll = WorldModel(net).rollout(2)
    roll.reset(torch.zeros(2, *GRID, dtype=torch.long))
    a = net.action_mean.expand(2, 7).clone()
    a[0, 0] = net.action_high[0] + 1.0
    a[1, 2] = net.action_low[2] - 5.0
    a[1, 5] = 1e9
    roll.step(a)
    assert roll.last_clip_count == 3 and roll.clip_count == 3
    roll.step(net.action_mean.expand(2, 7))
    assert roll.last_clip_count == 0 and roll.clip_count == 3


def test_tiny_training_reduces_loss():
    torch.manual_seed(0)
    n = GRID[0] * GRID[1]
    eps = []
    for i in range(4):  # tokens shift by the sign of action dim 0: learnable
        acts = torch.randn(12, 7)
        frames = [torch.randint(0, V, (n,))]
        for a in acts:
            frames.append((frames[-1] + (1 if a[0] > 0 else 2)) % V)
        eps.append(Episode(f"e{i}", "push", "ind", torch.stack(frames).numpy(), acts.numpy(),
                           (torch.arange(13) > 8).float().numpy(), np.zeros((13, 10), np.float32)))
    net = WorldModelNet(WMSpec(kind="action", vocab_size=V, grid=GRID, dim=32, depth=1, heads=2, window=4))
    net.set_action_stats(torch.cat([torch.from_numpy(e.actions) for e in eps]))
    sampler = ClipSampler(eps, 4, {"push": torch.zeros(384).numpy()}, seed=0)
    res = train_world_model(net, sampler, steps=60, batch_size=8, lr=3e-3, weight_decay=0.0, done_weight=1.0,
                            done_kind="bce", seed=0, device="cpu")
    first, last = res["history"][0], res["final"]
    assert last["ce"] < 0.7 * first["ce"] and last["done"] < first["done"]
