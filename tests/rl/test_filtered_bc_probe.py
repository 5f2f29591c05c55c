"""scripts/filtered_bc_probe.py's selection: every success, or only those of initial states that also failed."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from filtered_bc_probe import successes  # noqa: E402


def _rollouts(d: Path, outcomes: list[list[bool]]) -> None:
    """Groups of episodes (one initial state each); a successful episode i has i + 1 steps, its actions all i."""
    rows, i = [], 0
    for g, group in enumerate(outcomes):
        for ok in group:
            rows.append({"i": i, "group": g, "steps": i + 1, "success": ok})
            if ok:
                np.savez(d / f"{i:05d}.npz", actions=np.full((i + 1, 7), i, np.float32),
                         proprio=np.zeros((i + 1, 10), np.float32))
            i += 1
    (d / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_mixed_keeps_only_the_successes_of_states_that_also_failed(tmp_path):
    # state 0 always succeeds (episodes 0, 1), state 1 is mixed (2 succeeds, 3 fails), state 2 never (4, 5)
    _rollouts(tmp_path, [[True, True], [True, False], [False, False]])
    obs, actions, n = successes([tmp_path], "all")
    assert n == 2 + 1 and sorted(set(actions[:, 0].tolist())) == [0.0, 1.0, 2.0] and len(obs["proprio"]) == 1 + 2 + 3
    obs, actions, n = successes([tmp_path], "mixed")
    assert n == 1 and set(actions[:, 0].tolist()) == {2.0} and actions.shape == (3, 7)


def test_no_success_is_a_clear_error(tmp_path):
    _rollouts(tmp_path, [[False, False]])
    with pytest.raises(ValueError, match="no successful episodes"):
        successes([tmp_path], "all")
