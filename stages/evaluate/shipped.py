"""Which policy the rl stage shipped: PPO's, or SFT's after PPO failed its acceptance test.

With ``rl.accept_episodes`` the rl stage may save the SFT policy's weights as ``policy.zip``
(``stages/rl/acceptance.py``); the evaluation's "PPO" row is then SFT's policy, and the report says so
instead of crediting PPO with SFT's success.
"""
from __future__ import annotations

import json
from pathlib import Path

from stages.collect.tasks import TITLES
from stages.evaluate.report import html_table, markdown_table

SFT_SHIPPED = " [SFT's weights: PPO failed the acceptance test]"


def read_acceptance(rl_dir: Path) -> dict | None:
    """The rl stage's acceptance.json; None when the test was off."""
    path = Path(rl_dir) / "acceptance.json"
    return json.loads(path.read_text()) if path.is_file() else None


def shipped_label(label: str, acceptance: dict | None) -> str:
    """The PPO row's name, marked when the rl stage shipped SFT's weights."""
    return label + SFT_SHIPPED if acceptance is not None and acceptance["kept"] == "sft" else label


def acceptance_metrics(acceptance: dict | None) -> dict:
    """``shipped/*`` metrics: 1 when the evaluated "ppo" policy is PPO's own, and the test's figures."""
    if acceptance is None:
        return {}
    d = acceptance["difference"]
    return {"shipped/ppo": int(acceptance["kept"] == "ppo"), "shipped/accept_difference": d["diff"],
            "shipped/accept_difference_lo": d["lo"], "shipped/accept_difference_hi": d["hi"],
            "shipped/accept_episodes": acceptance["episodes"]}


def acceptance_section(acceptance: dict) -> tuple[str, str]:
    """(markdown, html body) of the report section on the acceptance test."""
    d = acceptance["difference"]
    kept = "PPO's policy" if acceptance["kept"] == "ppo" else "SFT's weights (the PPO row above is SFT's policy)"
    text = (f"Before shipping, the rl stage ran SFT and PPO on {d['n']} IND validation states (evaluate seed "
            f"{acceptance['evaluate_seed']}, disjoint from this evaluation's): SFT {acceptance['sft_success']:.2f}, "
            f"PPO {acceptance['ppo_success']:.2f}, PPO minus SFT {d['diff']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}] "
            f"({d['better']} states only PPO solved, {d['worse']} only SFT); margin {acceptance['margin']:+.2f}: "
            f"it shipped {kept}.")
    header = ["task", "validation states", "SFT", "PPO"]
    body = [[TITLES.get(t, t), str(v["episodes"]), f"{v['sft']:.2f}", f"{v['ppo']:.2f}"]
            for t, v in sorted(acceptance["by_task"].items())]
    return text + "\n\n" + markdown_table(header, body), f"<p>{text}</p>" + html_table(header, body)
