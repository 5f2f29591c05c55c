"""Errors a user can cause: each names what is wrong, and nothing runs."""
from __future__ import annotations

import pytest


def _fails(ws, *args):
    r = ws.cli(*args, check=False)
    assert r.returncode == 2, r
    assert "Traceback" not in r.stderr
    assert ws.executions() == []
    return r.stderr


def test_unknown_stage_in_until_lists_known_ones(ws):
    err = _fails(ws, "run", "--until", "trainwm")
    assert "--until: unknown stage 'trainwm'" in err and "collect, tokenize, train_wm, goals, rl, evaluate" in err


@pytest.mark.parametrize("flag", ["--only", "--from", "--force"])
def test_unknown_stage_in_other_flags(ws, flag):
    assert "unknown stage 'nope'" in _fails(ws, "run", flag, "nope")


def test_unknown_config_key_names_its_path(ws):
    ws.spec.write_text(ws.spec.read_text().replace("config: {value: 3}", "config: {valeu: 3}"))
    err = _fails(ws, "run")
    assert "train_wm.valeu: unknown key" in err and "allowed keys: value" in err


def test_wrong_type_names_its_path(ws):
    err = _fails(ws, "run", "--set", "rl.value=many")
    assert "rl.value" in err and "integer" in err


def test_unknown_top_level_key(ws):
    ws.spec.write_text(ws.spec.read_text() + "stagse: {}\n")
    err = _fails(ws, "dag")
    assert "stagse: unknown key" in err and "allowed top-level keys" in err


def test_cycle_in_needs_is_named(ws):
    ws.spec.write_text(ws.spec.read_text().replace("needs: [collect], config: {value: 2}", "needs: [collect, goals], config: {value: 2}"))
    err = _fails(ws, "dag")
    assert "cycle in needs" in err and "tokenize needs goals needs train_wm needs tokenize" in err


def test_unknown_needs_reference(ws):
    ws.spec.write_text(ws.spec.read_text().replace("needs: [tokenize]", "needs: [tokenise]"))
    assert "stages.train_wm.needs: unknown stage 'tokenise'" in _fails(ws, "dag")


def test_set_on_missing_key_fails_before_anything_runs(ws):
    err = _fails(ws, "run", "--set", "rl.rewrd=rule")
    assert "rl.rewrd" in err and "allowed keys" in err
    assert not (ws.store / "collect").exists()


def test_set_on_unknown_stage_and_malformed_set(ws):
    assert "unknown stage 'rll'" in _fails(ws, "run", "--set", "rll.reward=rule")
    assert "expected stage.key=value" in _fails(ws, "run", "--set", "reward")


def test_malformed_yaml_names_the_file(ws):
    ws.spec.write_text("stages: [unclosed\n")
    assert "pipeline.yaml: not valid YAML" in _fails(ws, "dag")


def test_unknown_profile_and_sweep(ws):
    assert "unknown profile" in _fails(ws, "run", "--profile", "huge")
    assert "unknown sweep" in _fails(ws, "sweep", "rewardz")
    assert "not an axis of sweep 'rewards'" in _fails(ws, "sweep", "rewards", "--axis", "rl.sead=[0]")
    assert "at least one value" in _fails(ws, "sweep", "rewards", "--axis", "rl.seed=3")


def test_missing_stage_module_is_a_clear_error(ws):
    ws.spec.write_text(ws.spec.read_text().replace("ts.goals", "ts.goalz"))
    err = _fails(ws, "run")
    assert "stage 'goals': cannot import module 'ts.goalz'" in err


def test_a_stage_named_like_a_store_directory_is_refused(ws):
    ws.spec.write_text(ws.spec.read_text().replace("  goals:    {", "  partial:  {").replace("needs: [goals, train_wm]", "needs: [partial, train_wm]"))
    r = ws.cli("status", check=False)
    assert r.returncode == 2 and "stages.partial: the name is reserved" in r.stderr and not (ws.store / "partial").exists()
