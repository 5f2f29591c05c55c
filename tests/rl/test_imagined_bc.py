"""stages/rl/imagined_bc.py: every demonstration frame gets one imagined twin, 1..horizon steps from a real frame."""
import numpy as np
import pytest
import torch

from stages.rl.imagined_bc import Chunk, chunks, imagined_pairs, imagined_twins
from stages.sft.data import Demo
from tests.rl.tiny import REST_PROPRIO, frames, obs_fn, tiny_action_wm, tiny_tokenizer


def test_chunks_cover_every_frame_with_an_action_after_it_once():
    cs = chunks([5, 1, 9], 3)
    assert cs == [Chunk(0, 0, 3), Chunk(0, 3, 1), Chunk(2, 0, 3), Chunk(2, 3, 3), Chunk(2, 6, 2)]
    covered = sorted((c.demo, c.start + m + 1) for c in cs for m in range(c.steps))
    assert covered == [(0, j) for j in range(1, 5)] + [(2, j) for j in range(1, 9)]  # frame 0 is real; T' has no action
    with pytest.raises(ValueError, match="horizon must be >= 1"):
        chunks([5], 0)


def _demos(tok, lengths):
    rng = np.random.default_rng(0)
    out = []
    for d, n in enumerate(lengths):
        third, wrist = frames(n + 1, seed=d)
        out.append(Demo(f"ep{d}", ["push the cube", "pull the cube"][d % 2], tok.encode(third, wrist).numpy(),
                        np.repeat(REST_PROPRIO[None], n + 1, axis=0), rng.uniform(-1, 1, (n, 7)).astype(np.float32)))
    return out


def test_a_twin_one_step_from_a_restart_is_the_model_imagining_that_step_from_the_real_frame():
    tok = tiny_tokenizer()
    wm = tiny_action_wm(tok)
    demos = _demos(tok, [6, 4])
    tokens, proprio, idx = imagined_twins(wm, demos, horizon=2, batch=2)  # batches split chunks across demonstrations
    assert sorted(map(tuple, idx)) == [(0, j) for j in range(1, 6)] + [(1, j) for j in range(1, 4)]
    assert tokens.shape == (8, *demos[0].tokens.shape[1:]) and proprio.shape == (8, 10)
    from stages.common.action_space import executed

    for d, j in ((0, 3), (1, 1)):  # frames one step after a restart (restarts at 0, 2, 4)
        roll = wm.rollout(1)
        roll.reset(torch.as_tensor(demos[d].tokens[j - 1:j]).long())
        out = roll.step(torch.as_tensor(executed(demos[d].actions[j - 1:j])))
        row = int(np.flatnonzero((idx[:, 0] == d) & (idx[:, 1] == j))[0])
        assert np.array_equal(tokens[row], out.tokens[0].numpy())


def test_imagined_pairs_carry_the_demonstrated_action_of_their_frame():
    tok = tiny_tokenizer()
    demos = _demos(tok, [5, 3])
    fn = obs_fn(tok)
    obs, actions = imagined_pairs(tiny_action_wm(tok), fn, demos, horizon=4)
    _, _, idx = imagined_twins(tiny_action_wm(tok), demos, 4)
    assert len(actions) == len(idx) == 4 + 2
    np.testing.assert_array_equal(actions, np.stack([demos[d].actions[j] for d, j in idx]))
    assert set(obs) == {"codes", "proprio", "instruction"} and len(obs["codes"]) == len(actions)


def test_imagined_bc_needs_a_world_model_reward():
    from stages.rl import Config

    assert Config(imagined_bc_epochs=2).imagined_bc_epochs == 2
    with pytest.raises(ValueError, match="imagined_bc_epochs=2 teaches the policy"):
        Config(reward="rule", imagined_bc_epochs=2)
