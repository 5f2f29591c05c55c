"""The stage end to end on tiny fake upstream artifacts: checkpoints, metrics, figure, loadable models."""
import json
import math

import torch

from pipeline.context import StageContext
from stages.train_wm import Config, run
from stages.train_wm.rollout import load_world_model
from tests.train_wm.fake_upstream import FakeDataset, install_fake_collect, make_tokenize_artifact

TINY = dict(dim=32, depth=1, heads=2, head_depth=1, window=4, control_tokens=2, action_steps=30, text_steps=20, batch_size=4, proprio_steps=30,
            eval_episodes=2, eval_starts=1, frame_skip=2)


def _finite(metrics: dict) -> list[str]:
    bad = []
    for k, v in metrics.items():
        if isinstance(v, float) and not math.isfinite(v) and "precision" not in k and "recall" not in k and "auroc" not in k:
            bad.append(k)
    return bad


def test_stage_writes_checkpoints_metrics_and_figure(tmp_path, monkeypatch):
    install_fake_collect(monkeypatch)
    tok_dir = make_tokenize_artifact(tmp_path / "tokenize", FakeDataset())
    out = tmp_path / "out"
    out.mkdir()
    ctx = StageContext(stage="train_wm", config=Config(**TINY), inputs={"collect": tmp_path / "collect", "tokenize": tok_dir},
                       out=out, seed=0)
    run(ctx)
    for name in ("action_wm.pt", "text_wm.pt", "proprio_head.pt", "text_embeddings.json", "split.json", "metrics.json",
                 "frames.png"):
        assert (out / name).is_file(), name
    m = json.loads((out / "metrics.json").read_text())
    assert not _finite(m), _finite(m)
    for split in ("heldout_ind", "ood"):
        for hz in (1, 5, 15):
            for row in ("wm", "copy_last", "tokenizer"):
                assert math.isfinite(m[f"action_wm/{split}/h{hz}/{row}/psnr"])
            assert math.isfinite(m[f"action_wm/{split}/h{hz}/wm_minus_copy/psnr"])
        assert m[f"action_wm/{split}/extreme_actions/finite"] == 1.0
        assert m[f"action_wm/{split}/extreme_actions/clip_fraction"] > 0.9
        assert 0.0 <= m[f"action_wm/{split}/done/brier"] <= 1.0
    assert (m["action_wm/train_steps"], m["text_wm/train_steps"]) == (30, 20)  # separate budgets
    for split in ("heldout_ind", "ood"):  # the proprioception head, open loop, next to copy-last
        assert m[f"proprio/{split}/h1/tcp_error_cm/head"] >= 0 and m[f"proprio/{split}/h15/tcp_error_cm/copy_last"] > 0
    action_wm = load_world_model(out, "action")
    nxt = action_wm.next_proprio(torch.zeros(2, 10), torch.zeros(2, 7), torch.zeros(2, 8, 8, dtype=torch.long))
    assert nxt.shape == (2, 10) and torch.isfinite(nxt).all()
    assert m["action_wm/history"][-1]["ce"] < m["action_wm/history"][0]["ce"]
    wm = load_world_model(out, "text")
    roll = wm.rollout(2)
    roll.reset(torch.zeros(2, 8, 8, dtype=torch.long), wm.text_embedding(["push the red cube", "a new instruction"]))
    step = roll.step()
    assert step.tokens.shape == (2, 8, 8) and step.done_prob.shape == (2,)
    assert wm.spec.frame_skip == 2 and load_world_model(out, "action").spec.frame_skip == 2  # consumers read it here
