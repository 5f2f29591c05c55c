"""train_wm resumes a killed run from its training checkpoints and ends where an uninterrupted run ends."""
import json

import numpy as np
import pytest
import torch

from pipeline.checkpoints import Checkpoints
from pipeline.context import StageContext
from stages.train_wm import Config, run
from stages.train_wm.data import ClipSampler, Episode
from stages.train_wm.model import WMSpec, WorldModelNet
from stages.train_wm.train import train_world_model
from tests.train_wm.fake_upstream import FakeDataset, install_fake_collect, make_tokenize_artifact
from tests.train_wm.test_stage import TINY


class Killed(Exception):
    """Stands for a kill -9 right after a checkpoint was published."""


def _episodes(vocab: int, n: int) -> list[Episode]:
    gen = torch.Generator().manual_seed(0)
    eps = []
    for i in range(3):
        acts = torch.randn(10, 7, generator=gen)
        frames = torch.randint(0, vocab, (11, n), generator=gen)
        eps.append(Episode(f"e{i}", "push", "ind", frames.numpy(), acts.numpy(), (torch.arange(11) > 7).float().numpy(),
                           np.zeros((11, 10), np.float32)))
    return eps


def _train(episodes, spec, steps=12, resume=None, save=None, seed=3):
    torch.manual_seed(0)
    net = WorldModelNet(spec)
    net.set_action_stats(torch.cat([torch.from_numpy(e.actions) for e in episodes]))
    sampler = ClipSampler(episodes, spec.window, {"push": np.zeros(384, np.float32)}, seed)
    result = train_world_model(net, sampler, steps=steps, batch_size=2, lr=1e-3, weight_decay=0.05, done_weight=1.0,
                               done_kind="bce", seed=seed, device="cpu", changed_weight=4.0, done_balance=True,
                               context_noise=0.1, resume=resume, save=save, save_every=4)
    return net, result


def test_the_loop_resumed_from_a_mid_training_state_ends_with_the_uninterrupted_weights_history_and_rng():
    spec = WMSpec(kind="action", vocab_size=16, grid=(4, 4), dim=16, depth=1, heads=2, head_depth=1, mlp_ratio=2,
                  window=4, control_tokens=2, frame_skip=1)
    episodes = _episodes(16, 16)
    states = []
    ref, ref_result = _train(episodes, spec, save=states.append)
    ref_rng = torch.get_rng_state()
    assert [s["step"] for s in states] == [4, 8, 12]  # every save_every steps and after the last one
    torch.manual_seed(123)  # the resumed process starts from other weights and another global RNG state
    resumed, result = _train(episodes, spec, resume=states[1])
    for k, v in ref.state_dict().items():
        assert torch.equal(v, resumed.state_dict()[k]), k
    assert result["history"] == ref_result["history"] and result["final"] == ref_result["final"]
    assert torch.equal(torch.get_rng_state(), ref_rng)
    done, done_result = _train(episodes, spec, resume=states[2])  # finished: nothing left to train
    assert all(torch.equal(v, done.state_dict()[k]) for k, v in ref.state_dict().items())
    assert done_result["history"] == ref_result["history"]


def _stage(tmp_path, name, monkeypatch, partial=None):
    out = tmp_path / name
    out.mkdir()
    ctx = StageContext(stage="train_wm", config=Config(**TINY),
                       inputs={"collect": tmp_path / "collect", "tokenize": tmp_path / "tokenize"},
                       out=out, seed=0, partial=partial)
    run(ctx)
    return out


def test_the_stage_killed_during_the_text_world_model_resumes_and_commits_what_an_uninterrupted_run_commits(
        tmp_path, monkeypatch):
    install_fake_collect(monkeypatch)
    make_tokenize_artifact(tmp_path / "tokenize", FakeDataset())
    reference = _stage(tmp_path, "reference", monkeypatch)

    partial = tmp_path / "partial"
    real_save = Checkpoints.save
    saved = []

    def save_then_kill(self, name):  # killed after the text model's 9th of 20 steps was saved, before its 10th
        saved.append(name)
        if saved.count("text_wm") == 10:
            raise Killed(name)
        return real_save(self, name)

    monkeypatch.setattr(Checkpoints, "save", save_then_kill)
    with pytest.raises(Killed):
        _stage(tmp_path, "killed", monkeypatch, partial)
    assert saved.count("action_wm") == 15  # every 30 // 12 = 2 steps, the last one after the last step
    monkeypatch.setattr(Checkpoints, "save", real_save)
    assert sorted(Checkpoints(partial).names()) == ["action_wm", "text_wm"]

    resumed = _stage(tmp_path, "resumed", monkeypatch, partial)
    for name in ("action_wm.pt", "text_wm.pt", "proprio_head.pt"):
        a, b = torch.load(reference / name, weights_only=False), torch.load(resumed / name, weights_only=False)
        for k, v in a["state_dict"].items():
            assert torch.equal(v, b["state_dict"][k]), (name, k)
    ref_m, res_m = (json.loads((d / "metrics.json").read_text()) for d in (reference, resumed))
    differ = sorted(k for k in ref_m if ref_m[k] != res_m.get(k) and "seconds" not in k)
    assert not differ, differ
