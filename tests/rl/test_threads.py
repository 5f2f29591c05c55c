"""The training stages' torch thread counts come from their configs (in the key), not from the cores
the executor gave the node: on a CPU the count changes the floating-point reductions, so the weights
(docs/rl.md, "The thread count is part of the result")."""
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import stages.rl as rl
import stages.sft as sft
import stages.train_wm as train_wm
import stages.wm_play as wm_play
from pipeline.plan import Project

ROOT = Path(__file__).resolve().parents[2]
FIELDS = {"train_wm": (train_wm, "train_threads"), "sft": (sft, "threads"), "wm_play": (wm_play, "threads"),
          "rl": (rl, "threads")}


class _Stop(Exception):
    pass


def _threads_at(monkeypatch, stage, first_load: str, threads: int, jobs: int) -> int:
    """The torch thread count when ``stage.run`` reaches ``first_load`` (stubbed to stop the run there)."""
    seen = []

    def load(*args, **kwargs):
        seen.append(torch.get_num_threads())
        raise _Stop

    monkeypatch.setattr(first_load, load)
    before = torch.get_num_threads()
    try:
        with pytest.raises(_Stop):
            stage.run(SimpleNamespace(config=stage.Config(threads=threads), device="cpu", jobs=jobs, input=str))
    finally:
        torch.set_num_threads(before)
    return seen[0]


@pytest.mark.parametrize("jobs,threads", [(1, 2), (2, 1)])
def test_rl_and_sft_run_on_their_configs_threads_whatever_the_executor_gave_them(monkeypatch, jobs, threads):
    assert _threads_at(monkeypatch, rl, "stages.rl.inputs.RLInputs.load", threads, jobs) == threads
    assert _threads_at(monkeypatch, sft, "stages.collect.dataset.Dataset", threads, jobs) == threads


@pytest.mark.parametrize("stage", sorted(FIELDS))
def test_the_thread_count_is_in_the_key_of_its_stage_and_of_nothing_upstream(tmp_path, stage):
    project = Project(ROOT / "pipeline.yaml", store=tmp_path)
    field = FIELDS[stage][1]

    def keys(n):
        return {node.stage: node.key for node in project.plan(["rl"], "toy", {stage: {field: n}}, "t")}

    one, two = keys(1), keys(2)
    assert one[stage] != two[stage]
    upstream = set(project.order[:project.order.index(stage)]) & set(one)
    assert {s: one[s] for s in upstream} == {s: two[s] for s in upstream}


@pytest.mark.parametrize("stage", sorted(FIELDS))
def test_a_thread_count_below_one_is_a_config_error(stage):
    module, field = FIELDS[stage]
    with pytest.raises(ValueError, match=field):
        module.Config(**{field: 0})
