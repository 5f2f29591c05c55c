"""The world model fine-tuned on the SFT policy's play (stages/wm_play): a copy is trained and the
original left alone; downstream stages load the fine-tuned weights, or train_wm's when play is off."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from stages.train_wm.data import Episode
from tests.rl.tiny import text_embeddings, tiny_action_wm, tiny_tokenizer

WM_CONFIG = {"window": 4, "seed": 0, "batch_size": 4, "weight_decay": 0.05, "done_weight": 1.0, "done_loss": "bce",
             "changed_weight": 4.0, "done_balance": True}


def episodes(tok, n: int, kind: str, success: bool, seed: int) -> list[Episode]:
    rng = np.random.default_rng(seed)
    h, w = tok.grid
    out = []
    for i in range(n):
        t = 6
        done = np.zeros(t + 1, np.float32)
        done[-1] = float(success)
        out.append(Episode(f"{kind}-{i}", "push the cube", "ind", rng.integers(0, tok.vocab_size, (t + 1, h * w)),
                           rng.uniform(-1, 1, (t, 7)).astype(np.float32), done,
                           rng.normal(size=(t + 1, 10)).astype(np.float32), kind))
    return out


def test_the_fine_tune_trains_a_copy_and_leaves_the_loaded_model_alone(tmp_path):
    from stages.wm_play.play import finetune_on_play

    (tmp_path / "manifest.json").write_text(json.dumps({"key_inputs": {"config": WM_CONFIG}}))
    (tmp_path / "text_embeddings.json").write_text(json.dumps(text_embeddings(["push the cube"])))
    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    before = {k: v.clone() for k, v in wm.net.state_dict().items()}
    tuned, result = finetune_on_play(wm, tmp_path, episodes(tok, 3, "optimal", True, 0), episodes(tok, 2, "play", False, 1),
                                     steps=3, lr=1e-3, weight=2, device="cpu")
    assert tuned is not wm and tuned.net is not wm.net and not tuned.net.training
    assert all(torch.equal(v, wm.net.state_dict()[k]) for k, v in before.items())  # the original is untouched
    assert any(not torch.equal(v, tuned.net.state_dict()[k]) for k, v in before.items())
    assert tuned.proprio_head is not None and result["final"]["ce"] > 0


def test_a_fine_tune_resumed_from_its_mid_run_state_ends_with_the_uninterrupted_weights(tmp_path):
    """The stage's ``finetune`` checkpoint: the state saved after step 2 of 5, handed back as ``resume``
    to a fresh copy of the loaded model (another global RNG state, as in a new process), ends with
    the weights and history of the run that was never interrupted."""
    from stages.wm_play.play import finetune_on_play

    (tmp_path / "manifest.json").write_text(json.dumps({"key_inputs": {"config": WM_CONFIG}}))
    (tmp_path / "text_embeddings.json").write_text(json.dumps(text_embeddings(["push the cube"])))
    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    train, play = episodes(tok, 3, "optimal", True, 0), episodes(tok, 2, "play", False, 1)
    states: list[dict] = []
    torch.manual_seed(0)
    ref, ref_result = finetune_on_play(wm, tmp_path, train, play, steps=5, lr=1e-3, weight=2, device="cpu",
                                       save=states.append, save_every=2)
    assert [s["step"] for s in states] == [2, 4, 5]
    class Counted:  # the steps the resumed call trains itself, and those it takes as done
        def __init__(self):
            self.done, self.skipped = 0, 0

        def update(self, n=1):
            self.done += n

        def resumed(self, n):
            self.skipped += n

        def postfix(self, **kv):
            pass

    torch.manual_seed(123)
    counted = Counted()
    resumed, result = finetune_on_play(wm, tmp_path, train, play, steps=5, lr=1e-3, weight=2, device="cpu",
                                       resume=states[0], progress=counted)
    assert (counted.skipped, counted.done) == (2, 3)  # steps 3-5 trained, 1-2 restored
    for k, v in ref.net.state_dict().items():
        assert torch.equal(v, resumed.net.state_dict()[k]), k
    assert result["history"] == ref_result["history"]


def test_play_instructions_need_a_text_embedding(tmp_path):
    from stages.wm_play.play import finetune_on_play

    (tmp_path / "manifest.json").write_text(json.dumps({"key_inputs": {"config": WM_CONFIG}}))
    (tmp_path / "text_embeddings.json").write_text(json.dumps(text_embeddings(["pull the cube"])))
    tok = tiny_tokenizer()
    with pytest.raises(ValueError, match="without a text embedding"):
        finetune_on_play(tiny_action_wm(tok), tmp_path, [], episodes(tok, 1, "play", False, 0), steps=1, lr=1e-3,
                         weight=1, device="cpu")


def _train_wm_dir(path, tok):
    from stages.train_wm.proprio import CHECKPOINT, save_head
    from stages.train_wm.rollout import CHECKPOINTS, save_world_model

    wm = tiny_action_wm(tok)
    path.mkdir()
    save_world_model(wm.net, path / CHECKPOINTS["action"], {"decode_steps": 3})
    save_head(wm.proprio_head, path / CHECKPOINT)
    (path / "text_embeddings.json").write_text(json.dumps(text_embeddings(["push the cube"])))
    return wm


def test_downstream_stages_load_the_fine_tuned_weights_or_train_wms(tmp_path):
    from stages.train_wm.rollout import CHECKPOINTS, save_world_model
    from stages.wm_play import WM_PLAY_JSON, action_world_model

    tok = tiny_tokenizer()
    base = _train_wm_dir(tmp_path / "train_wm", tok)
    off, on = tmp_path / "off", tmp_path / "on"
    off.mkdir(), on.mkdir()
    (off / WM_PLAY_JSON).write_text(json.dumps({"finetuned": False, "episodes": 0}))
    tuned = tiny_action_wm(tok)
    with torch.no_grad():
        for p in tuned.net.parameters():
            p.add_(0.5)
    save_world_model(tuned.net, on / CHECKPOINTS["action"])
    (on / WM_PLAY_JSON).write_text(json.dumps({"finetuned": True, "episodes": 4}))

    plain = action_world_model(off, tmp_path / "train_wm")
    assert all(torch.equal(v, base.net.state_dict()[k]) for k, v in plain.net.state_dict().items())
    played = action_world_model(on, tmp_path / "train_wm")
    assert all(torch.equal(v, tuned.net.state_dict()[k]) for k, v in played.net.state_dict().items())
    # the rest is train_wm's: decoding settings, proprioception head, text embeddings
    assert played.decode_steps == 3 and played.proprio_head is not None


def test_a_missing_or_foreign_fine_tune_is_named(tmp_path):
    from stages.train_wm.model import WMSpec, WorldModelNet
    from stages.train_wm.rollout import CHECKPOINTS, save_world_model
    from stages.wm_play import WM_PLAY_JSON, action_world_model

    tok = tiny_tokenizer()
    _train_wm_dir(tmp_path / "train_wm", tok)
    with pytest.raises(FileNotFoundError, match="wm_play.json"):
        action_world_model(tmp_path, tmp_path / "train_wm")
    other = tmp_path / "other"
    other.mkdir()
    wider = WorldModelNet(WMSpec(kind="action", vocab_size=tok.vocab_size, grid=tok.grid, dim=32, depth=1, heads=2,
                                 head_depth=1, mlp_ratio=2, window=4, control_tokens=2))
    save_world_model(wider, other / CHECKPOINTS["action"])
    (other / WM_PLAY_JSON).write_text(json.dumps({"finetuned": True, "episodes": 4}))
    with pytest.raises(ValueError, match="not fine-tuned from"):
        action_world_model(other, tmp_path / "train_wm")


def test_play_is_on_by_default_and_zero_turns_it_off():
    from stages.wm_play import Config

    assert Config().episodes == 384 and Config().steps == 2000
    assert Config(episodes=0).episodes == 0
    with pytest.raises(ValueError):
        Config(episodes=-1)
    with pytest.raises(ValueError):
        Config(wm_play_episodes=8)  # the old rl option's name: strict configs name it


def test_the_play_does_not_depend_on_rl_code():
    # the fine-tune is shared by every reward point of a seed and costs about an hour at `small`:
    # an edit under stages/rl must not change its key (rl's does depend on it)
    from pipeline.keys import source_closure

    root = Path(__file__).resolve().parents[2]
    play = {str(f.relative_to(root)) for f in source_closure("stages.wm_play", [root])}
    assert "stages/wm_play/play.py" in play and not [f for f in play if f.startswith("stages/rl/")]
    assert "stages/wm_play/__init__.py" in {str(f.relative_to(root)) for f in source_closure("stages.rl", [root])}
