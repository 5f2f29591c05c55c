"""Untrained but real tokenizer and action world model at a tiny size, for rl unit tests."""
from __future__ import annotations

import numpy as np
import torch

from stages.common.proprio import proprio_from_state
from stages.rl.wm_env import Start
from stages.sft.observation import ObservationFn

# the Panda's TCP pointing down above the table, fingers open (a typical first frame)
REST_PROPRIO = proprio_from_state(np.array([[-0.1, 0.0, 0.18, 0.0, 1.0, 0.0, 0.0]]), np.array([[0.0] * 7 + [0.04, 0.04]]))[0]


def tiny_tokenizer(image_size: int = 64):
    from stages.tokenize.model import ModelSpec, TokenizerNet
    from stages.tokenize.tokenizer import Tokenizer

    torch.manual_seed(0)
    return Tokenizer(TokenizerNet(ModelSpec(image_size=image_size, bits=6, channels=(8, 16, 16), res_blocks=1)))


def tiny_action_wm(tok):
    from stages.train_wm.model import WMSpec, WorldModelNet
    from stages.train_wm.proprio import ProprioHead
    from stages.train_wm.rollout import WorldModel

    torch.manual_seed(0)
    net = WorldModelNet(WMSpec(kind="action", vocab_size=tok.vocab_size, grid=tok.grid, dim=16, depth=1, heads=2,
                               head_depth=1, mlp_ratio=2, window=4, control_tokens=2))
    net.set_action_stats(torch.rand(64, 7) * 2 - 1)
    return WorldModel(net.eval(), decode_steps=2, proprio_head=ProprioHead(tok.bits, tok.grid, hidden=16, frame_dim=8).eval())


def text_embeddings(instructions) -> dict:
    rng = np.random.default_rng(0)
    return {s: rng.normal(size=384).astype(np.float32).tolist() for s in instructions}


def frames(n: int, size: int = 64, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Structured uint8 views (n, size, size, 3): coloured blocks on a table."""
    rng = np.random.default_rng(seed)
    third = np.full((n, size, size, 3), 120, np.uint8)
    third[:, size // 2 :] = (150, 140, 120)
    for i in range(n):
        r, c = rng.integers(0, size - 16, size=2)
        third[i, r : r + 16, c : c + 16] = rng.integers(0, 255, size=3)
    wrist = third[:, ::-1].copy()
    return third, wrist


def starts_for(tok, n: int = 3) -> list[Start]:
    third, wrist = frames(n)
    tokens = tok.encode(third, wrist).numpy()
    return [Start(i % 2, ["push the cube", "pull the cube"][i % 2], tokens[i], REST_PROPRIO, ["push/scene_0", "pull/scene_1"][i % 2])
            for i in range(n)]


def obs_fn(tok) -> ObservationFn:
    return ObservationFn(tok, text_embeddings(["push the cube", "pull the cube"]))
