"""The real pipeline at toy scale, second file: a sweep that shares the session's toy store's stages,
its policies on fresh states, an acceptance test that ships SFT, and the world-model probe scripts on
an exported store (``tests/e2e/toy_store.py``; it runs beside ``test_toy_pipeline.py`` under xdist).
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tests.e2e.toy_store import REPO, actions, cli, shown, store  # noqa: F401  (store: the fixture)

pytestmark = [pytest.mark.slow, pytest.mark.sim]


def test_reward_sweep_reuses_the_shared_stages(store):
    # the imagined-success check is the fixture run's to test; here it would cost ~15 s in each of 12 rl nodes
    # two of the sweep's three seeds (--axis): the sharing is the same, and each seed costs an sft, a
    # wm_play and four rl nodes
    proc = cli(store, "sweep", "rewards", "--until", "rl", "--profile", "toy", "--set", "rl.precision_envs=0",
               "--axis", "sft.seed+wm_play.seed+rl.seed=[0, 1]")
    acts = actions(proc)
    for s in ("collect", "tokenize", "train_wm", "goals"):
        assert acts[(s, "ran")] == 0 and acts[(s, "cached")] == 1
    assert acts[("rl", "ran")] + acts[("rl", "cached")] == 8
    # one SFT policy and one play-tuned world model per seed, shared by the four reward points
    # (seed 0's are the fixture run's)
    for s in ("sft", "wm_play"):
        assert acts[(s, "ran")] == 1 and acts[(s, "cached")] == 1, s
    # PPO in the simulator reads no play-tuned world model (stages.rl.unread_needs): not in its key
    readers = {json.loads(m.read_text())["key_inputs"]["config"]["reward"]: "wm_play" in json.loads(m.read_text())["key_inputs"]["inputs"]
               for m in (store / "rl").glob("*/*/manifest.json")}
    assert readers == {"rule": False, "wm": True, "embedding": True, "proxy": True}
    out = next((store / "sweeps" / "rewards").glob("*/results.json")).parent
    table = json.loads((out / "results.json").read_text())
    assert sorted({r["rl.reward"] for r in table["rows"]}) == ["embedding", "proxy", "rule", "wm"]
    report = (out / "report.md").read_text()  # the sweep report hook, on the real rl artifacts
    assert "Cost per method" in report and "spearman_progress" in report
    assert (out / "training_curves.png").is_file() and (out / "reward_diagnostics.png").is_file()


def test_a_sweeps_policies_are_evaluated_on_fresh_states_into_files_the_table_pairs(store, tmp_path):
    # one point of the rewards sweep (cached when the test above ran first)
    point = ["rewards", "--profile", "toy", "--set", "rl.precision_envs=0", "--axis", "sft.seed+wm_play.seed+rl.seed=[0]",
             "--axis", "rl.reward=[wm]"]
    cli(store, "sweep", *point, "--until", "rl")
    driver = [sys.executable, str(REPO / "scripts" / "fresh_state_sweep.py"), *point, "--store", str(store),
              "--folder", str(tmp_path), "--tag", "toy", "--splits", "ood", "--episodes", "1", "--max-steps", "5", "--jobs", "1"]
    first = subprocess.run(driver, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert first.returncode == 0, first.stdout + first.stderr[-4000:]
    assert "[2/2]" in first.stdout and '"stem": "rewards-wm"' in first.stdout
    sys.path.insert(0, str(REPO / "scripts"))
    from fresh_state_table import episodes, episodes_file

    sft_rows = episodes(episodes_file(tmp_path, "sft", 0, "ood", "toy"))
    ppo_rows = episodes(episodes_file(tmp_path, "rewards-wm", 0, "ood", "toy"))
    assert {r["policy"] for r in sft_rows} == {"sft"} and {r["policy"] for r in ppo_rows} == {"ppo"}
    # the same fresh states for both policies: the pairing's premise
    assert sorted((r["task"], r["scene_id"], r["seed"]) for r in sft_rows) == sorted((r["task"], r["scene_id"], r["seed"]) for r in ppo_rows)
    again = subprocess.run(driver, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "[1/" not in again.stdout and again.stdout.count("done ") == 2, again.stdout

    # the states the two policies disagree on (at toy scale mostly agree on), looked at: both rerun there;
    # each side given its own sft artifact (as for an ensemble against one member), so the positional one
    # is never read
    line = next(x.split() for x in first.stdout.splitlines() if "evaluate_sft.py" in x and "--rl" in x)
    flips = subprocess.run([sys.executable, str(REPO / "scripts" / "flip_strips.py"), *line[1:3], str(tmp_path / "no-such-sft"),
                            "--method", str(episodes_file(tmp_path, "rewards-wm", 0, "ood", "toy")),
                            "--method-rl", line[line.index("--rl") + 1], "--method-sft", line[3],
                            "--baseline", str(episodes_file(tmp_path, "sft", 0, "ood", "toy")), "--baseline-sft", line[3],
                            "--per-way", "1", "--same", "1", "--max-steps", "5", "--jobs", "1", "--out", str(tmp_path / "strips")],
                           cwd=REPO, capture_output=True, text=True, timeout=900)
    assert flips.returncode == 0, flips.stdout + flips.stderr[-4000:]
    shown_states = sorted((tmp_path / "strips").glob("*.png"))
    assert 1 <= len(shown_states) <= 4  # one per kind at most; every pair falls in some kind
    # the rerun is the file's episode again (every reset rebuilds the scene): each outcome reproduces
    assert f"outcomes reproduced by the rerun: {2 * len(shown_states)} of {2 * len(shown_states)}" in flips.stdout, flips.stdout
    assert all(p.name in (tmp_path / "strips" / "index.md").read_text() for p in shown_states)


def test_an_acceptance_test_that_ppo_cannot_pass_ships_the_sft_policy(store):
    sets = ["--set", "rl.accept_episodes=1", "--set", "rl.accept_margin=1", "--set", "rl.precision_envs=0"]
    cli(store, "run", "--profile", "toy", "--until", "evaluate", *sets)
    rl = shown(store, "rl", *sets)
    table = json.loads((rl / "acceptance.json").read_text())
    tasks = json.loads((shown(store, "sft") / "policy.json").read_text())["tasks"]
    episodes = [json.loads(x) for x in (rl / "acceptance_episodes.jsonl").read_text().splitlines()]
    assert table["kept"] == "sft" and table["episodes"] == len(episodes) == 2 * len(tasks)  # one state per task, both policies
    assert {(e["task"], e["seed"]) for e in episodes if e["policy"] == "sft"} == \
           {(e["task"], e["seed"]) for e in episodes if e["policy"] == "ppo"}  # paired on the same states
    m = json.loads((rl / "metrics.json").read_text())
    assert m["accept/kept_ppo"] is False and m["accept/episodes"] == len(episodes)
    import torch

    from stages.sft.policy import POLICY_FILE, load_policy

    shipped, sft = load_policy(rl / "policy.zip"), load_policy(shown(store, "sft") / POLICY_FILE)
    shipped.set_training_mode(False), sft.set_training_mode(False)  # SFT's dropout off, as in evaluation
    space = sft.observation_space
    space.seed(0)
    obs = [space.sample() for _ in range(8)]
    batch = {k: torch.as_tensor(np.stack([o[k] for o in obs])) for k in obs[0]}
    with torch.no_grad():
        assert torch.allclose(shipped.mean_action(batch), sft.mean_action(batch), atol=1e-6)  # SFT's actions, not PPO's
    from stages.evaluate.shipped import SFT_SHIPPED

    ev = shown(store, "evaluate", *sets)  # the report does not credit PPO with SFT's policy
    assert json.loads((ev / "metrics.json").read_text())["shipped/ppo"] == 0
    report = (ev / "report.md").read_text()
    assert SFT_SHIPPED in report and "Acceptance test before shipping" in report


def test_the_world_model_probe_trains_and_fine_tunes_on_an_exported_store(store, tmp_path):
    """scripts/wm_size_probe.py: export (with the SFT policy's play), train a model from scratch on it and
    fine-tune train_wm's on the play; the checkpoints load as the stage's and the fine-tune moved the weights."""
    import os

    import numpy as np
    import torch

    from pipeline.spec import load_spec
    from stages.train_wm.rollout import load_net

    ups = {s: shown(store, s) for s in ("collect", "tokenize", "train_wm", "sft")}
    data, out = tmp_path / "data.pt", tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    run = lambda *a: subprocess.run([sys.executable, "scripts/wm_size_probe.py", *map(str, a)], cwd=REPO,  # noqa: E731
                                    capture_output=True, text=True, timeout=900, env=env)
    p = run("export", ups["collect"], ups["tokenize"], ups["train_wm"], "--out", data, "--play-sft", ups["sft"],
            "--play-episodes", 2, "--play-steps", 4)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "2 play episodes" in p.stdout
    base = ups["train_wm"] / "action_wm.pt"
    p = run("train", data, '{"action_steps": 3}', "--with-play", 1, "--finetune", base, "--finetune-steps", 2,
            "--baseline", base, "--save-dir", out)
    assert p.returncode == 0, p.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert set(results) == {"baseline", "action_wm_play", "m0"}
    for name in ("baseline", "action_wm_play", "m0"):
        assert results[name]["eval"], name  # at least one split evaluated
        for split, m in results[name]["eval"].items():
            tf = m["teacher_forced"]
            assert np.isfinite(tf["ce"]) and 0.0 <= tf["acc"] <= 1.0, (name, split, tf)
            assert 0.0 <= m["done"]["auroc"] <= 1.0 or np.isnan(m["done"]["auroc"]), (name, split, m["done"])
    tuned, orig = load_net(out / "action_wm_play.pt"), load_net(base)
    assert tuned.spec == orig.spec == load_net(out / "m0.pt").spec  # the artifact's config, not the defaults
    assert any(not torch.equal(v, orig.state_dict()[k]) for k, v in tuned.state_dict().items())
    for split, m in results["m0"]["eval"].items():  # the planner's actions imagined open loop, whole episodes
        imag = m["imagined_success"]
        assert imag["episodes"] > 0, (split, imag)
        assert 0 <= imag["both"] <= min(imag["imagined_done"], imag["real_success"]) <= imag["episodes"], imag

    # scripts/arm_consistency_probe.py on the same export: an arm locator fitted on its real frames, the policy
    # check with the imagined and replayed proprioception recorded, a gap per imagined success
    p = subprocess.run([sys.executable, "scripts/arm_consistency_probe.py", str(data), *(str(ups[s]) for s in
                        ("collect", "tokenize", "train_wm", "sft")), "--envs", "2", "--steps", "4", "--locator-steps", "20"],
                       cwd=REPO, capture_output=True, text=True, timeout=900, env=env)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "arm locator on real" in p.stdout and "veto above 2.0 cm" in p.stdout, p.stdout[-2000:]

    # encode: the tokenize artifact's tokenizer applied to a collect afresh, as the stage encodes and splits
    # (here the same collect, so the very same tokens and held-out episodes)
    enc = tmp_path / "enc"
    p = run("encode", ups["collect"], ups["tokenize"], "--out", enc)
    assert p.returncode == 0, p.stderr[-3000:]
    assert np.array_equal(np.load(enc / "tokens.npy"), np.load(ups["tokenize"] / "tokens.npy"))
    for name in ("index.json", "split.json"):
        assert json.loads((enc / name).read_text()) == json.loads((ups["tokenize"] / name).read_text()), name

    # without a train_wm artifact (a tokenize artifact of another grid, or an encoded folder): train_wm's
    # Config and the overrides (here the toy profile's size: the defaults are the small profile's, whose
    # evaluation alone takes minutes on 2 cores), instructions encoded afresh; with --tokenizer: decoded PSNR
    # per horizon and a frame strip; --exclude-kinds leaves the grasp-misses out of the second model's
    # training clips only
    bare, out2 = tmp_path / "bare.pt", tmp_path / "out2"
    toy = load_spec(REPO / "pipeline.yaml").profiles["toy"]["train_wm"]
    p = run("export", ups["collect"], enc, "--out", bare)
    assert p.returncode == 0, p.stderr[-3000:]
    p = run("train", bare, json.dumps({**toy, "action_steps": 2}), "--tokenizer", enc, "--save-dir", out2)
    assert p.returncode == 0, p.stderr[-3000:]
    p = run("train", bare, json.dumps({**toy, "action_steps": 1}), "--exclude-kinds", "grasp_miss",
            "--save-dir", tmp_path / "out3")
    assert p.returncode == 0, p.stderr[-3000:]
    kept = json.loads((tmp_path / "out3" / "results.json").read_text())["m0"]
    assert kept["exclude_kinds"] == ["grasp_miss"]
    assert 0 < kept["train_episodes"] < json.loads((out2 / "results.json").read_text())["m0"]["train_episodes"]
    ev = json.loads((out2 / "results.json").read_text())["m0"]["eval"]
    for split, m in ev.items():
        acc = m["open_loop_token_acc"]
        psnrs = [v for k, v in acc.items() if k.endswith("/psnr") or k.endswith("/psnr_third")]
        assert psnrs and all(np.isfinite(v) and v > 0 for v in psnrs), (split, acc)
    assert (out2 / "m0_strip.png").stat().st_size > 0
    p = run("export", ups["collect"], ups["tokenize"], "--out", bare, "--play-sft", ups["sft"])
    assert p.returncode != 0 and "needs the train_wm artifact" in p.stderr
