"""scripts/wm_closed_loop.py's agreement: the done head as a judge of the policy's closed-loop success."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from wm_closed_loop import agreement  # noqa: E402


def _row(task: str, real: bool, imagined: bool) -> dict:
    return {"env": f"{task}/scene", "sim_success_at": 7 if real else -1, "wm_done_at": 5 if imagined else -1}


def test_agreement_counts_real_successes_where_imagined_and_where_not_per_task():
    rows = ([_row("push", True, True)] * 3 + [_row("push", False, True)] + [_row("push", True, False)] * 2
            + [_row("pick_place", False, False)] * 4)
    a = agreement(rows)
    assert a["all"]["imagined"] == 4 and a["all"]["imagined_and_real"] == 3
    assert a["all"]["precision"] == pytest.approx(0.75) and a["all"]["precision_lo"] < 0.75 < a["all"]["precision_hi"]
    assert (a["all"]["real_where_not_imagined"], a["all"]["not_imagined"]) == (2, 6)
    assert (a["push"]["real_where_not_imagined"], a["push"]["not_imagined"]) == (2, 2)
    assert a["pick_place"]["precision"] is None and a["pick_place"]["real"] == 0
