"""scripts/fresh_state_sweep.py: which policies of a sweep it evaluates, where their files go, how it resumes."""
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

from fresh_state_sweep import Policy, drain, manifest_entries, policies, store_tag, target  # noqa: E402
from fresh_state_table import episodes_file, file_prefix  # noqa: E402


def test_the_files_it_writes_are_the_ones_the_table_reads(tmp_path):
    for split in ("ind", "ood"):
        out, done = target(tmp_path, file_prefix("calibration_gate-wm_gated", 3, split, "c6f250d4"), "2026-12-03")
        assert not done
        out.write_text("")
        assert episodes_file(tmp_path, "calibration_gate-wm_gated", 3, split, "c6f250d4") == out
        # a method whose stem extends another's is not mistaken for it
        assert target(tmp_path, file_prefix("calibration_gate-wm", 3, split, "c6f250d4"), "2026-12-03")[1] is False


def test_a_finished_file_is_skipped_and_an_interrupted_one_resumes_under_its_own_date(tmp_path):
    prefix = file_prefix("sft", 0, "ood", "tag")
    (tmp_path / f"{prefix}2026-12-03.jsonl.partial").write_text("")
    out, done = target(tmp_path, prefix, "2026-12-04")  # a later session resumes the earlier partial
    assert (out.name, done) == (f"{prefix}2026-12-03.jsonl", False)
    out.write_text("")
    assert target(tmp_path, prefix, "2026-12-04") == (out, True)
    (tmp_path / f"{prefix}2026-12-05.jsonl").write_text("")
    with pytest.raises(SystemExit, match="expected at most one"):
        target(tmp_path, prefix, "2026-12-05")


def test_the_manifest_names_only_seeds_whose_method_and_sft_files_are_all_finished(tmp_path):
    pols = [Policy("sft", s, (), None) for s in (0, 1)] + [Policy("g-wm", s, (), Path("rl")) for s in (0, 1)]
    for name in ("sft_s0", "sft_ood_s0", "g-wm_s0", "g-wm_ood_s0", "sft_ood_s1", "g-wm_ood_s1"):
        (tmp_path / f"{name}_t_2026-12-03.jsonl").write_text("")
    (tmp_path / "g-wm_s1_t_2026-12-03.jsonl.partial").write_text("")  # seed 1's IND episodes are unfinished
    assert manifest_entries(tmp_path, pols, ["ood", "ind"], "t") == [
        {"label": "g-wm", "stem": "g-wm", "baseline": "sft", "seeds": [0], "tag": "t"}]
    assert manifest_entries(tmp_path, pols, ["ood"], "t") == [
        {"label": "g-wm", "stem": "g-wm", "baseline": "sft", "seeds": [0, 1], "tag": "t", "splits": ["ood"]}]


class FakeStore:
    """A store holding the (stage, key)s it is given; an rl artifact holds its rl.json."""

    def __init__(self, root: Path, held: dict[tuple[str, str], str | None]):
        self.root, self.held = root, held
        for (stage, key), method in held.items():
            self.path(stage, key).mkdir(parents=True)
            if stage == "rl":
                (self.path(stage, key) / "rl.json").write_text(json.dumps({"reward": "wm", "method": method}))

    def path(self, stage, key):
        return self.root / stage / key

    def lookup(self, stage, key):
        return SimpleNamespace(state="ok" if (stage, key) in self.held else "missing", path=self.path(stage, key))


def point(label, sft_key, sft_seed, rl_key):
    nodes = [SimpleNamespace(stage="collect", key="c0ffee", config={}), SimpleNamespace(stage="tokenize", key="t1", config={}),
             SimpleNamespace(stage="sft", key=sft_key, config={"seed": sft_seed}), SimpleNamespace(stage="rl", key=rl_key, config={})]
    return SimpleNamespace(label=label, nodes=nodes)


def test_sft_is_offered_as_soon_as_it_exists_and_ppo_once_its_rl_artifact_does(tmp_path):
    held = {("collect", "c0ffee"): None, ("tokenize", "t1"): None, ("sft", "s0"): None, ("sft", "s1"): None,
            ("rl", "r0"): "wm", ("rl", "r0g"): "wm_gated"}
    project = SimpleNamespace(store=FakeStore(tmp_path, held))
    points = [point("p0", "s0", 0, "r0"), point("p0g", "s0", 0, "r0g"), point("p1", "s1", 1, "r1"), point("p2", "s2", 2, "r2")]
    pols, waiting, collect_key = policies(project, "g", points)
    assert [(p.stem, p.seed) for p in pols] == [("sft", 0), ("g-wm", 0), ("g-wm_gated", 0), ("sft", 1)]
    assert waiting == ["p1", "p2"] and collect_key == "c0ffee"
    assert pols[1].rl == tmp_path / "rl" / "r0" and pols[1].dirs == pols[0].dirs
    # two SFT policies under one seed would write the same files
    held[("sft", "s0b")] = None
    project = SimpleNamespace(store=FakeStore(tmp_path / "b", held))
    with pytest.raises(SystemExit, match="share sft.seed 0"):
        policies(project, "g", [point("p0", "s0", 0, "r0"), point("q0", "s0b", 0, "r0g")])


def test_follow_evaluates_each_policy_as_its_artifact_lands_out_of_domain_first_and_stops_when_none_waits():
    sft, ppo = Policy("sft", 0, (), None), Policy("g-wm", 0, (), Path("rl"))
    landed, ran, slept = [[sft], [sft], [sft], [sft, ppo]], [], []  # the store as the sweep fills it, one look at a time

    def plan(verbose):
        pols = landed[0] if len(landed) == 1 else landed.pop(0)
        todo = [(p, sp, Path(f"{p.stem}_{sp}")) for sp in ("ood", "ind") for p in pols if f"{p.stem}_{sp}" not in ran]
        return todo, ([] if ppo in pols else ["p0"]), pols, "t"

    pols, tag = drain(plan, lambda p, sp, out: ran.append(out.name), follow=60, sleep=slept.append)
    assert ran == ["sft_ood", "sft_ind", "g-wm_ood", "g-wm_ind"] and slept == [60] and (pols, tag) == ([sft, ppo], "t")
    # without --follow it evaluates what is there and stops, though a point waits
    landed[:], ran[:], slept[:] = [[sft]], [], []
    assert drain(plan, lambda p, sp, out: ran.append(out.name), follow=0, sleep=slept.append) == ([sft], "t")
    assert ran == ["sft_ood", "sft_ind"] and slept == []
    # an evaluation that leaves no file stops the loop instead of repeating it
    landed[:], ran[:] = [[sft]], []
    with pytest.raises(SystemExit, match="still missing"):
        drain(plan, lambda p, sp, out: None, follow=0, sleep=slept.append)


def test_two_builds_of_one_collect_key_get_two_default_tags(tmp_path):
    """A store rebuilt at the same collect key is another draw of every stage: its fresh-state files
    must not be taken for the old store's (a finished file is skipped, so they would pair)."""
    from pipeline.store import Store

    key = "c6f250d4ab2c" + "0" * 52
    tags = []
    for build in ("a", "b"):
        store = Store(tmp_path / build)
        assert store_tag(store, key) == "cc6f250d4"  # nothing committed yet: the key alone
        staging = store.staging("collect", key)
        (staging / "episodes.txt").write_text("the same data\n")
        store.commit(staging, "collect", key, {"config": {}}, extra={"build": build})
        tags.append(store_tag(store, key))
    assert tags[0] != tags[1] and all(t.startswith("cc6f250d4") and len(t) == 13 and "_" not in t for t in tags)
    assert store_tag(Store(tmp_path / "a"), key) == tags[0]  # stable for one store
