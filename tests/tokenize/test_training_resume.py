"""tokenize resumes a killed run from its training checkpoint and ends where an uninterrupted run ends."""
import json

import numpy as np
import pytest
import torch

import stages.tokenize as tokenize
from pipeline.checkpoints import Checkpoints
from pipeline.context import StageContext
from stages.tokenize.model import ModelSpec, TokenizerNet
from stages.tokenize.train import TrainSettings, train
from tokenize_fakes import FakeDataset, write_collect_artifact
from test_tokenize_stage import TOY

SPEC = ModelSpec(image_size=32, bits=6, channels=(8, 16), res_blocks=1)
SETTINGS = TrainSettings(steps=12, batch_size=4, lr=2e-3, warmup_steps=2, weight_decay=0.01, recon_loss="l1",
                         lpips_weight=1.0, lpips_batch=2, entropy_weight=0.1, commitment_weight=0.25, grad_clip=1.0)


class Killed(Exception):
    """Stands for a kill -9 right after a checkpoint was published."""


def _frames():
    ds = FakeDataset(n_ind=3, n_ood=0, T=5, size=32)
    eps = [ds.load(e.episode_id) for e in ds.episodes]
    return np.concatenate([e.third for e in eps]), np.concatenate([e.wrist for e in eps])


def _train(resume=None, save=None, settings=SETTINGS, frames=None):
    torch.manual_seed(0)
    net = TokenizerNet(SPEC)
    third, wrist = frames if frames is not None else _frames()
    hist = train(net, third, wrist, settings, seed=5, resume=resume, save=save, save_every=5)
    return net, hist


def test_the_loop_resumed_from_a_mid_training_state_ends_with_the_uninterrupted_weights_and_history():
    states = []
    ref, ref_hist = _train(save=states.append)
    ref_rng = torch.get_rng_state()
    assert [s["step"] for s in states] == [5, 10, 12]  # every save_every steps and after the last one
    torch.manual_seed(123)  # the resumed process starts from other weights and another global RNG state
    resumed, hist = _train(resume=states[0])
    for k, v in ref.state_dict().items():
        assert torch.equal(v, resumed.state_dict()[k]), k
    assert (hist.recon, hist.lpips, hist.entropy) == (ref_hist.recon, ref_hist.lpips, ref_hist.entropy)
    assert torch.equal(torch.get_rng_state(), ref_rng)
    done, done_hist = _train(resume=states[2])  # finished: nothing left to train
    assert all(torch.equal(v, done.state_dict()[k]) for k, v in ref.state_dict().items())
    assert done_hist.recon == ref_hist.recon


def test_a_checkpoint_of_other_frames_or_settings_is_refused_by_name():
    states = []
    _train(save=states.append)
    third, wrist = _frames()
    n = len(third)
    with pytest.raises(ValueError, match=f"tokenize checkpoint from training on {n} frames.*this run trains on {n - 1}"):
        _train(resume=states[0], frames=(third[:-1], wrist[:-1]))
    with pytest.raises(ValueError, match="not the same run"):
        _train(resume=states[0], settings=TrainSettings(**{**SETTINGS.__dict__, "lr": 1e-3}))


def _stage(tmp_path, name, partial=None):
    out = tmp_path / name
    out.mkdir()
    cfg = tokenize.Config(**TOY)
    tokenize.run(StageContext(stage="tokenize", config=cfg, inputs={"collect": tmp_path / "collect"}, out=out,
                              seed=cfg.seed, partial=partial))
    return out


def test_the_stage_killed_mid_training_resumes_and_commits_what_an_uninterrupted_run_commits(tmp_path, monkeypatch):
    write_collect_artifact(tmp_path / "collect", FakeDataset(n_ind=5, n_ood=2, T=6, size=64))
    reference = _stage(tmp_path, "reference")

    partial = tmp_path / "partial"
    real_save = Checkpoints.save
    saved = []

    def save_then_kill(self, name):  # killed after step 7 of 12 was saved, before step 8's save
        saved.append(name)
        if len(saved) == 8:
            raise Killed(name)
        return real_save(self, name)

    monkeypatch.setattr(Checkpoints, "save", save_then_kill)
    with pytest.raises(Killed):
        _stage(tmp_path, "killed", partial)
    monkeypatch.setattr(Checkpoints, "save", real_save)
    assert Checkpoints(partial).names() == ["tokenizer"]
    assert torch.load(partial / "tokenizer" / "state.pt", weights_only=False)["step"] == 7  # saved every step of 12

    resumed = _stage(tmp_path, "resumed", partial)
    a, b = (torch.load(d / "tokenizer.pt", weights_only=False) for d in (reference, resumed))
    assert a.keys() == b.keys()
    for k, v in a["state_dict"].items():
        assert torch.equal(v, b["state_dict"][k]), k
    assert np.array_equal(np.load(reference / "tokens.npy"), np.load(resumed / "tokens.npy"))
    ref_m, res_m = (json.loads((d / "metrics.json").read_text()) for d in (reference, resumed))
    differ = sorted(k for k in ref_m if ref_m[k] != res_m.get(k) and "second" not in k)  # timings aside
    assert not differ, differ


def test_the_stage_killed_mid_encoding_encodes_only_the_chunks_it_had_not_saved(tmp_path, monkeypatch):
    from stages.tokenize.tokenizer import Tokenizer

    write_collect_artifact(tmp_path / "collect", FakeDataset(n_ind=5, n_ood=2, T=6, size=64))
    monkeypatch.setattr(tokenize, "ENCODE_CHUNK", 2)  # 7 episodes: chunks of 2, 2, 2, 1
    reference = _stage(tmp_path, "reference")

    partial = tmp_path / "partial"
    real_save, real_encode = Checkpoints.save, Tokenizer.encode

    def save_then_kill(self, name):  # killed while encoding the third chunk, after two were saved
        if name == "encode-2":
            raise Killed(name)
        return real_save(self, name)

    monkeypatch.setattr(Checkpoints, "save", save_then_kill)
    with pytest.raises(Killed):
        _stage(tmp_path, "killed", partial)
    monkeypatch.setattr(Checkpoints, "save", real_save)
    assert Checkpoints(partial).names() == ["encode-0", "encode-1", "tokenizer"]

    encoded = []  # frames per Tokenizer.encode call; the metrics' frames do not go through it
    monkeypatch.setattr(Tokenizer, "encode", lambda self, third, *a, **k: encoded.append(len(third)) or real_encode(self, third, *a, **k))
    resumed = _stage(tmp_path, "resumed", partial)
    assert len(encoded) == 3, encoded  # episodes 4, 5 and 6; the first four were read back
    assert np.array_equal(np.load(reference / "tokens.npy"), np.load(resumed / "tokens.npy"))
    assert (reference / "index.json").read_text() == (resumed / "index.json").read_text()
    ref_m, res_m = (json.loads((d / "metrics.json").read_text()) for d in (reference, resumed))
    assert {k: v for k, v in ref_m.items() if k.startswith("all/")} == {k: v for k, v in res_m.items() if k.startswith("all/")}

    np.save(partial / "encode-0" / "tokens.npy", np.zeros((1, 1, 1), np.uint16))  # damaged: its digest no longer matches
    encoded.clear()
    again = _stage(tmp_path, "again", partial)
    assert len(encoded) == 2, encoded  # that chunk alone is encoded again
    assert np.array_equal(np.load(reference / "tokens.npy"), np.load(again / "tokens.npy"))
