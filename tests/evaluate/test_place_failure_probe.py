"""scripts/place_failure_probe.py: an episode is filed under the furthest placing phase it reached, in order
(a grasp must come before a lift, a lift before being over the target), and the table counts them."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))

from place_failure_probe import PHASES, first_close, furthest_phase, table  # noqa: E402


def _steps(*flags: str) -> list[dict]:
    """Per-step states from strings of the letters g (grasped), l (lifted), o (over the target)."""
    return [{"grasped": "g" in f, "lifted": "l" in f, "over": "o" in f, "dist": 0.1} for f in flags]


@pytest.mark.parametrize("flags, success, phase", [
    (("", "", ""), False, "never grasped"),
    (("", "o", "l"), False, "never grasped"),                       # pushed over the target, never held: no grasp
    (("g", "g", ""), False, "grasped, never lifted"),
    (("g", "gl", "l"), False, "lifted, never over the target"),    # dropped while carrying it
    (("gl", "", "o"), False, "over the target, not placed"),        # lifted, then over the target later
    (("o", "gl", ""), False, "lifted, never over the target"),      # over the target only before the lift
    (("gl", "glo", "o"), True, "success"),
])
def test_furthest_phase(flags, success, phase):
    assert furthest_phase(_steps(*flags), success) == phase


def test_first_close_is_read_in_the_state_the_command_was_issued_in():
    steps = [{"reach": r, "above": a} for r, a in ((0.20, 0.15), (0.09, 0.08), (0.012, 0.004), (0.01, 0.0))]
    assert first_close(steps, [1.0, 0.4, -0.7, -1.0]) == {"close_step": 2, "close_reach_cm": 1.2, "close_above_cm": 0.4}
    assert first_close(steps, [1.0, 1.0, 0.2]) == {"close_step": None, "close_reach_cm": None, "close_above_cm": None}


def test_table_counts_each_phase_per_split_and_task():
    rows = [{"split": "ind", "task": "move_to_aim", "phase": p, "closest_cm": c, "reach_cm": r}
            for p, c, r in zip(PHASES, (10.0, 8.0, 6.0, 2.0, 1.0), (9.0, 1.0, 1.5, 2.5, 0.5))]
    rows.append({"split": "ind", "task": "pick_place", "phase": "success", "closest_cm": 0.5})  # a row from before reach_cm
    out = table(rows).splitlines()
    assert out[2] == "| ind | move_to_aim | 5 | 1 | 1 | 1 | 1 | 1 | 6.0 | 1.5 |"
    assert out[3] == "| ind | pick_place | 1 | 0 | 0 | 0 | 0 | 1 | 0.5 | - |"


def test_a_task_the_policy_was_not_trained_on_is_refused(tmp_path):
    (tmp_path / "policy.json").write_text('{"tasks": ["push"], "frame_skip": 4}')
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "place_failure_probe.py"), str(tmp_path), str(tmp_path),
                          str(tmp_path)], capture_output=True, text=True, cwd=REPO)
    assert out.returncode != 0 and "not trained on ['pick_place', 'move_to_aim']" in out.stderr, out.stderr


@pytest.mark.sim
def test_hidden_carpet_leaves_the_view_and_keeps_the_layout():
    """--hide carpet: the purple carpet is gone from the third view, the object and the target's xy are where
    the same seed put them, and the env is back to normal after the block; --hide container puts the container
    under the table."""
    from place_failure_probe import UNDER_TABLE, hidden
    from stages.collect.envs import DEFAULT_SCENE
    from stages.collect.sim import make_task_env

    def look(env) -> tuple[int, np.ndarray, np.ndarray]:
        obs, _ = env.reset(seed=3)
        r, g, b = obs["third"].astype(int).transpose(2, 0, 1)  # (H, W) each, from (H, W, 3) uint8
        purple = ((b > g + 40) & (r > g + 20)).sum()  # the carpet's hue as rendered (176, 111, 202); the red cube's is not
        u = env.unwrapped
        return int(purple), u.obj.pose.p[0, :2].numpy().copy(), u._target_xy()[0].numpy().copy()

    env = make_task_env("move_to_aim", DEFAULT_SCENE)
    shown, obj, target = look(env)
    with hidden(["carpet"]):
        gone, obj_hidden, target_hidden = look(env)
    back, _, _ = look(env)
    with hidden(["container"]):  # white like the table's highlights: read its pose, not its pixels
        env.reset(seed=3)
        container_z = float(env.unwrapped.container.pose.p[0, 2])
    env.close()
    assert container_z == pytest.approx(UNDER_TABLE), container_z
    assert shown > 20 and back == shown, (shown, back)
    assert gone == 0, gone
    assert np.array_equal(obj, obj_hidden) and np.array_equal(target, target_hidden)


def test_hiding_an_unknown_actor_is_refused():
    from place_failure_probe import hidden

    with pytest.raises(ValueError, match="cannot hide \\['table'\\]"):
        with hidden(["table"]):
            pass
