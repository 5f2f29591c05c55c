"""The tokenize stage end to end on a tiny fake collect artifact (same interface as collect's Dataset)."""
import json
import math

import numpy as np
import pytest
from pydantic import ValidationError

import stages.tokenize as tokenize
from pipeline.context import StageContext
from tokenize_fakes import FakeDataset, write_collect_artifact

TOY = dict(channels=(8, 16, 32), bits=8, steps=12, batch_size=8, lpips_batch=2, eval_frames=16, warmup_steps=2, figure_frames=4)


def _run(tmp_path, ds, monkeypatch=None, **overrides):
    """Run the stage; on a real collect artifact written from ``ds`` unless ``monkeypatch`` is given."""
    if monkeypatch is not None:
        monkeypatch.setattr(tokenize, "open_dataset", lambda path: ds)
    else:
        write_collect_artifact(tmp_path / "collect", ds)
    out = tmp_path / "out"
    out.mkdir()
    cfg = tokenize.Config(**{**TOY, **overrides})
    tokenize.run(StageContext(stage="tokenize", config=cfg, inputs={"collect": tmp_path / "collect"}, out=out, seed=cfg.seed))
    return out


def test_stage_writes_tokens_index_metrics_and_figure(tmp_path):
    ds = FakeDataset(n_ind=5, n_ood=2, T=6, size=64)
    out = _run(tmp_path, ds)  # through stages.collect.dataset.Dataset on a real MCAP shard
    for name in ("tokenizer.pt", "tokens.npy", "index.json", "metrics.json", "recon.png", "split.json"):
        assert (out / name).is_file(), name

    m = json.loads((out / "metrics.json").read_text())
    for split in ("heldout_ind", "ood"):
        for view in ("third", "wrist"):
            for k in ("psnr", "ssim", "lpips"):
                assert math.isfinite(m[f"{split}/{view}_{k}"]), (split, view, k)
    assert 0 < m["all/code_usage"] <= 1 and m["all/code_perplexity"] >= 1 and m["train_seconds"] > 0
    assert m["all/frames"] == 7 * 7 and m["grid"] == [16, 8]  # one 8 x 8 grid per view

    split = json.loads((out / "split.json").read_text())
    ood = {e.episode_id for e in ds.episodes if e.split == "ood"}
    assert not ood & set(split["train"]) and not set(split["heldout"]) & set(split["train"]) and len(split["heldout"]) == 1

    store = tokenize.TokenStore(out)
    tok = tokenize.load_tokenizer(out)
    assert len(store) == 7 and store.grid == tok.grid and store.bits == tok.bits == 8
    for e in ds.episodes:
        ep = ds.load(e.episode_id)
        tokens = store.episode(e.episode_id)
        assert tokens.shape == (e.length + 1, 16, 8) and tokens.dtype == np.uint16
        assert np.array_equal(tokens, tok.encode(ep.third, ep.wrist).numpy())
    third, wrist = tok.decode(store.episode(ds.episodes[0].episode_id))  # uint16 memmap in, images out
    assert third.shape == wrist.shape == (ds.episodes[0].length + 1, 3, 64, 64)
    assert np.isfinite(third.numpy()).all() and tok.codes(store.episode(ds.episodes[0].episode_id)).shape[1] == 8
    with pytest.raises(KeyError, match="not in this token store"):
        store.episode("nope")


def test_stage_without_ind_episodes_fails_clearly(tmp_path, monkeypatch):
    ds = FakeDataset(n_ind=0, n_ood=2, T=3)
    with pytest.raises(ValueError, match="no IND episodes"):
        _run(tmp_path, ds, monkeypatch)


def test_config_is_strict_and_frozen():
    with pytest.raises(ValidationError):
        tokenize.Config(bitz=8)
    with pytest.raises(ValidationError):
        tokenize.Config(bits=17)
    assert all(f.description for f in tokenize.Config.model_fields.values())
