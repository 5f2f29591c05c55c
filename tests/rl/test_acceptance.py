"""The acceptance test's decision: paired on the same states, PPO kept only above the margin."""
import pytest

from stages.rl.acceptance import decide


def rows(policy, outcomes, task="push"):
    return [{"policy": policy, "task": task, "split": "ind", "scene_id": "s0", "seed": i, "success": bool(o)}
            for i, o in enumerate(outcomes)]


def test_ppo_is_kept_only_when_it_beats_sft_by_more_than_the_margin():
    sft = rows("sft", [1, 0, 0, 1, 0, 0, 1, 0])  # 3 / 8
    better = rows("ppo", [1, 1, 0, 1, 1, 0, 1, 0])  # 5 / 8: +0.25 on the same states
    d = decide(sft, better, margin=0.0)
    assert d["kept"] == "ppo" and d["difference"]["diff"] == pytest.approx(0.25)
    assert d["difference"]["better"] == 2 and d["difference"]["worse"] == 0
    assert d["sft_success"] == pytest.approx(3 / 8) and d["ppo_success"] == pytest.approx(5 / 8)
    assert decide(sft, better, margin=0.25)["kept"] == "sft"  # must exceed, not reach
    assert decide(sft, rows("ppo", [1, 0, 0, 1, 0, 0, 1, 0]), margin=0.0)["kept"] == "sft"  # a tie keeps SFT
    assert decide(sft, better, margin=1.0)["kept"] == "sft"


def test_only_shared_states_are_compared_per_task():
    sft = rows("sft", [0, 0]) + rows("sft", [1, 1], task="pull")
    ppo = rows("ppo", [1, 1, 1]) + rows("ppo", [1, 0], task="pull")  # push seed 2: SFT never ran it
    d = decide(sft, ppo, margin=0.0)
    assert d["difference"]["n"] == 4 and d["difference"]["diff"] == pytest.approx((2 - 1) / 4)
    assert d["by_task"] == {"pull": {"episodes": 2, "sft": 1.0, "ppo": 0.5}, "push": {"episodes": 2, "sft": 0.0, "ppo": 1.0}}
    with pytest.raises(ValueError, match="share no initial state"):
        decide(rows("sft", [1]), rows("ppo", [1], task="pull"), margin=0.0)


def test_evaluation_seeds_cannot_reach_the_acceptance_tests_validation_states():
    from pydantic import ValidationError

    from stages.evaluate import Config
    from stages.rl.acceptance import ACCEPT_SEED

    Config(seed=ACCEPT_SEED - 1)
    with pytest.raises(ValidationError):
        Config(seed=ACCEPT_SEED)


def test_the_validation_states_lie_at_evaluate_seed_60_plus_the_rl_seed():
    from stages.rl import Config as RlConfig
    from stages.rl.acceptance import ACCEPT_SEED, validation_config

    for seed in (0, 7):
        ecfg = validation_config(RlConfig(seed=seed, accept_episodes=3))
        assert (ecfg.seed, ecfg.episodes, ecfg.splits, ecfg.policies) == (ACCEPT_SEED + seed, 3, ["ind"], ["sft", "ppo"])


def test_the_acceptance_episodes_leave_the_stages_thread_count_as_they_found_it(monkeypatch, tmp_path):
    """The evaluate jobs' simulator sets one torch thread (right in an evaluate worker); inside the rl
    stage, which runs on its config's ``threads``, the imagined-success check after the test must not
    inherit it. The jobs here are fakes that do what the real ones do to the thread count."""
    from types import SimpleNamespace

    import torch

    import stages.evaluate.episodes as episodes
    import stages.evaluate.jobs as jobs
    from stages.rl import Config
    from stages.rl.acceptance import acceptance_test

    job = lambda policy: SimpleNamespace(policy=policy, seeds=[0, 1])  # noqa: E731

    def fake_run(j):
        torch.set_num_threads(1)
        return rows(j.policy, [1, 0])

    monkeypatch.setattr(jobs, "build_jobs", lambda *a, **k: [job("sft"), job("ppo")])
    monkeypatch.setattr(episodes, "run_job", fake_run)
    ctx = SimpleNamespace(input=lambda name: tmp_path, progress=lambda *a, **k: _Bar())
    inp = SimpleNamespace(device="cpu", tasks=["push"], sft_info={"frame_skip": 4})
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        result, got = acceptance_test(ctx, Config(accept_episodes=2), inp, tmp_path)
        assert torch.get_num_threads() == 2 and result["episodes"] == 4 and result["kept"] == "sft"
    finally:
        torch.set_num_threads(before)


class _Bar:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        pass
