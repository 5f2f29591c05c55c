"""The world model fine-tuned on the SFT policy's play (stages/rl/play.py): a copy is trained, the
original is left alone, and the option is refused where PPO does not train in the world model."""
from __future__ import annotations

import json

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
    from stages.rl.play import finetune_on_play

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


def test_play_instructions_need_a_text_embedding(tmp_path):
    from stages.rl.play import finetune_on_play

    (tmp_path / "manifest.json").write_text(json.dumps({"key_inputs": {"config": WM_CONFIG}}))
    (tmp_path / "text_embeddings.json").write_text(json.dumps(text_embeddings(["pull the cube"])))
    tok = tiny_tokenizer()
    with pytest.raises(ValueError, match="without a text embedding"):
        finetune_on_play(tiny_action_wm(tok), tmp_path, [], episodes(tok, 1, "play", False, 0), steps=1, lr=1e-3,
                         weight=1, device="cpu")


def test_play_is_refused_where_ppo_trains_in_the_simulator():
    from stages.rl import Config

    with pytest.raises(ValueError, match="trains in the simulator"):
        Config(reward="rule", wm_play_episodes=8)
    assert Config(wm_play_episodes=8).wm_play_steps == 2000
