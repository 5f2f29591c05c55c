"""The evaluation names the policy the rl stage shipped (stages/evaluate/shipped.py)."""
from stages.evaluate.shipped import SFT_SHIPPED, acceptance_metrics, acceptance_section, shipped_label
from stages.rl.acceptance import decide


def acceptance(sft: list[int], ppo: list[int]) -> dict:
    rows = lambda policy, wins: [{"policy": policy, "task": "push", "split": "ind", "scene_id": "s", "seed": i,  # noqa: E731
                                  "success": bool(w)} for i, w in enumerate(wins)]
    table = decide(rows("sft", sft), rows("ppo", ppo), margin=0.0)
    table.update({"episodes": 2 * len(sft), "seconds": 1.0, "evaluate_seed": 60})
    return table


def test_a_rejected_ppo_policy_is_named_as_sfts_weights():
    rejected, kept = acceptance([1, 1, 0, 0], [1, 0, 0, 0]), acceptance([1, 0, 0, 0], [1, 1, 0, 0])
    assert shipped_label("PPO", rejected) == "PPO" + SFT_SHIPPED
    assert shipped_label("PPO", kept) == shipped_label("PPO", None) == "PPO"
    assert acceptance_metrics(rejected)["shipped/ppo"] == 0 and acceptance_metrics(kept)["shipped/ppo"] == 1
    assert acceptance_metrics(None) == {}
    md, _ = acceptance_section(rejected)
    assert "shipped SFT's weights" in md and "PPO minus SFT -0.25" in md and "| Push | 4 | 0.50 | 0.25 |" in md
