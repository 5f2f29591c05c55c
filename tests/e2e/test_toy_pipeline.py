"""The real pipeline, all eight stages, at toy scale, through the real CLI (the session's toy store,
``tests/e2e/toy_store.py``): the stages' outputs, caching, resuming and the rl variants.

Slow by nature (every stage trains or simulates for real). A sweep, the acceptance test and the probe
scripts are in ``test_toy_sweeps_and_scripts.py``, which runs beside this file under xdist.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest

from tests.e2e.toy_store import REPO, STAGES, actions, artifact, cli, shown, store  # noqa: F401  (store: the fixture)

pytestmark = [pytest.mark.slow, pytest.mark.sim]


def test_all_eight_stages_produce_their_artifacts_and_the_report(store):
    ev = artifact(store, "evaluate")
    report = (ev / "report.md").read_text()
    assert "success rate" in report.lower() and "IND" in report and "OOD" in report
    assert (ev / "report.html").is_file() and (ev / "rollouts.png").is_file()
    results = [json.loads(x) for x in (ev / "results.jsonl").read_text().splitlines()]
    cells = {(r["policy"], r["split"], r["task"]) for r in results if "@" not in r["policy"] and r["split"] != "extra"}
    assert len(cells) > 2 and {f"rollout_{p}_{s}_{t}.gif" for p, s, t in cells} == {f.name for f in ev.glob("rollout_*.gif")}
    metrics = json.loads((ev / "metrics.json").read_text())
    assert any(k.startswith("success/ppo/all/ind") for k in metrics)
    assert any(k.startswith("success/sft/all/ind") for k in metrics)
    # how each episode ended: its longest run of resting steps, tallied per policy, split and outcome
    assert all(isinstance(r["rest_steps"], int) and 0 <= r["rest_steps"] <= r["steps"] for r in results)
    assert any(k.startswith("rest/sft/ind/") for k in metrics) and "came to rest" in report
    rl = json.loads((artifact(store, "rl") / "metrics.json").read_text())
    assert rl["ppo/param_change_relative"] > 0  # PPO changed the policy
    sft = json.loads((artifact(store, "sft") / "metrics.json").read_text())
    assert sft["pairs/train"] > 0 and len([k for k in sft if k.startswith("val/r2/")]) == 7
    wm = json.loads((artifact(store, "train_wm") / "metrics.json").read_text())
    assert wm["proprio/heldout_ind/h1/tcp_error_cm/head"] is not None
    assert rl["ppo/episodes"] > 0  # episodes ended, by the done head or by truncation
    assert rl["ppo/decoder_layout"] in ("default", "channels_last")  # what conv_layout timed faster on this CPU
    by_start = json.loads((artifact(store, "rl") / "success_by_start.json").read_text())
    assert by_start["unfinished_from"] > 0 and "ppo/success_first_fifth" in rl  # the unbiased training curve
    for stage in ("tokenize", "train_wm", "sft", "rl"):  # training curves for TensorBoard, and the command that shows them
        assert list((artifact(store, stage) / "tensorboard").glob("events.out.tfevents.*")), stage
    shown = cli(store, "show", "rl", "--profile", "toy").stdout
    assert "tensorboard --logdir" in shown


def test_failures_are_collected_as_negatives_and_never_demonstrations(store):
    """Near-misses and grasp-misses: collected, never successful, never SFT demonstrations, and train_wm
    reports its done head's false alarms on each kind."""
    from stages.collect.plans import FAILURE_KINDS

    episodes = [json.loads(x) for x in (artifact(store, "collect") / "episodes.jsonl").read_text().splitlines()]
    misses = {e["episode_id"] for e in episodes if e["kind"] in FAILURE_KINDS}
    assert {e["kind"] for e in episodes if e["episode_id"] in misses} == set(FAILURE_KINDS)
    assert not any(e["success"] for e in episodes if e["episode_id"] in misses)
    split = json.loads((artifact(store, "sft") / "split.json").read_text())
    demos = {i for ids in split.values() for i in ids}
    assert demos and not demos & misses
    wm = json.loads((artifact(store, "train_wm") / "metrics.json").read_text())
    for kind in FAILURE_KINDS:
        assert 0.0 <= wm[f"action_wm/ood/done/{kind}/false_alarm_rate"] <= 1.0, kind


def test_success_out_earns_lingering_for_every_reward_module(store):
    """On real successful episodes, with the toy run's real world model, goals and fitted heads: the
    discounted return of finishing beats that of hovering in the last frame before success until
    truncation, for every registered module (the environments pay ``success_return`` on success)."""
    from types import SimpleNamespace

    import numpy as np
    import torch

    from stages.common.frame_skip import frame_indices
    from stages.rl import Config
    from stages.rl.inputs import RLInputs
    from stages.rl.rewards import REGISTRY, EmbeddingHead, GoalDistance, ProxyCNN, RewardParts, success_return
    from stages.rl.rewards.fit import frame_set

    ctx = SimpleNamespace(input=lambda name: artifact(store, name), device="cpu")
    inp = RLInputs.load(ctx, Config())
    heads = torch.load(artifact(store, "rl") / "reward_heads.pt")
    parts = RewardParts(GoalDistance(*inp.goal_frames()), {"embedding": EmbeddingHead(inp.wm.spec.dim), "proxy": ProxyCNN()})
    for name, state in heads.items():
        parts.heads[name].load_state_dict(state)
    ids = [i for i, m in inp.meta.items() if m.success and m.kind == "optimal" and m.task in inp.tasks][:3]
    fs = frame_set(inp.wm, [inp.steps(i) for i in ids], "cpu")
    decoded, first_decoded = inp.tok.decode(fs.tokens), inp.tok.decode(fs.first_tokens)
    goal_rows = np.array([inp.env_of(ids[e]) for e in fs.episode])
    gamma = 0.99
    for e, eid in enumerate(ids):
        states = inp.dataset.load_states(eid)
        success = np.asarray(states["success"])[frame_indices(len(states["action"]), inp.frame_skip)][1:]
        s = int(np.argmax(success))  # frames 1..T: index of the first successful one
        horizon = len(success) + 10
        first, frames = fs.episode_batches(e, decoded, first_decoded, goal_rows)
        for name, cls in REGISTRY.items():
            module = cls.build(parts, Config(reward=name, gamma=gamma), num_envs=1)
            r = module.along(first, frames)  # (T,)
            prefix = sum(gamma**k * r[k] for k in range(s))
            finish = prefix + gamma**s * success_return(module.max_step_reward, horizon - (s + 1), gamma)
            linger = prefix + sum(gamma**k * r[s - 1] for k in range(s, horizon))
            assert finish >= linger, (name, eid, finish, linger)
            assert r.max() <= module.max_step_reward + 1e-6, (name, r.max(), module.max_step_reward)


def test_second_run_executes_nothing(store):
    again = actions(cli(store, "run", "--profile", "toy"))
    assert again == Counter({(s, "cached"): 1 for s in STAGES})


def test_adding_evaluation_scenes_reruns_only_evaluate(store):
    scene = '[{shape: cube, size: large, color: [0.9, 0.5, 0.1], color_name: orange, container: bowl, table: wood}]'
    proc = cli(store, "run", "--profile", "toy", "--set", f"evaluate.extra_scenes={scene}", "--set", "evaluate.splits=[extra]")
    acts = actions(proc)
    assert acts[("evaluate", "ran")] == 1 and sum(n for (s, a), n in acts.items() if a == "ran") == 1
    results = [json.loads(x) for x in (artifact(store, "evaluate") / "results.jsonl").read_text().splitlines()]
    assert {r["split"] for r in results if "@" not in r["policy"]} == {"extra"}
    assert any("orange" in r["instruction"] for r in results)


def test_same_seed_same_evaluation(store):
    path = shown(store, "evaluate")
    before = (path / "results.jsonl").read_text()
    proc = cli(store, "run", "--profile", "toy", "--force", "evaluate")
    assert actions(proc)[("evaluate", "ran")] == 1
    assert (path / "results.jsonl").read_text() == before  # --force keeps the key: same path, rerun from scratch


def test_changing_an_rl_setting_does_not_rerun_sft(store):
    acts = actions(cli(store, "run", "--profile", "toy", "--until", "rl", "--set", "rl.gamma=0.98",
                       "--set", "rl.precision_envs=0"))  # the imagined-success check is not this test's subject
    assert acts[("sft", "cached")] == 1 and acts[("sft", "ran")] == 0 and acts[("rl", "ran")] == 1
    assert acts[("wm_play", "cached")] == 1 and acts[("wm_play", "ran")] == 0


def test_the_demonstration_anchor_trains_on_sfts_own_training_pairs(store):
    cli(store, "run", "--profile", "toy", "--until", "rl", "--set", "rl.demo_bc_batches=2", "--set", "rl.precision_envs=0")
    m = json.loads((artifact(store, "rl") / "metrics.json").read_text())
    sft = json.loads((shown(store, "sft") / "metrics.json").read_text())
    assert m["demo_bc/pairs"] == sft["pairs/train"] > 0  # the pairs SFT trained on, read with its recipe
    assert m["demo_bc/loss_last"] >= 0.0  # it ran after the toy profile's one post-warm-up update


def test_filtered_bc_imitates_its_own_simulator_successes_and_ships_a_policy_evaluate_reads(store):
    sets = ["--set", "rl.algorithm=filtered_bc", "--set", "rl.reward=rule", "--set", "rl.fbc_rounds=2",
            "--set", "rl.precision_envs=0", "--set", "rl.diagnostics=none", "--set", "evaluate.world_model_figure=false"]
    acts = actions(cli(store, "run", "--profile", "toy", "--until", "evaluate", *sets))
    assert acts[("sft", "cached")] == 1 and acts[("rl", "ran")] == 1 and acts[("evaluate", "ran")] == 1
    rl = shown(store, "rl", *sets)
    assert json.loads((rl / "rl.json").read_text())["method"] == "rule_fbc"
    # ManiSkill only, nothing diagnosed or imagined: the run read (and is keyed by) no world model and no goals
    assert sorted(json.loads((rl / "manifest.json").read_text())["key_inputs"]["inputs"]) == ["collect", "sft", "tokenize"]
    assert shown(store, "rl", *sets, "--set", "train_wm.dim=48") == rl
    rounds = json.loads((rl / "filtered_bc.json").read_text())["rounds"]
    episodes = json.loads((rl / "episodes.json").read_text())
    sft = json.loads((shown(store, "sft") / "metrics.json").read_text())
    assert len(rounds) == 2 and sum(r["episodes"] for r in rounds) == len(episodes) > 0
    assert rounds[-1]["imitated_episodes"] == sum(e["success"] for e in episodes)  # every success so far, no failure
    assert rounds[-1]["own_pairs"] == sum(e["length"] for e in episodes if e["success"])
    assert all(r["demonstration_pairs"] == sft["pairs/train"] and r["epochs"] == 3 for r in rounds)
    snaps = json.loads((rl / "snapshots" / "index.json").read_text())
    assert len(snaps) == 2 and all((rl / s["path"]).is_file() for s in snaps)  # one policy per round
    import torch

    from stages.sft.policy import POLICY_FILE, load_policy

    fitted, first = load_policy(rl / "policy.zip"), load_policy(shown(store, "sft") / POLICY_FILE)
    fitted.set_training_mode(False), first.set_training_mode(False)
    space = first.observation_space
    space.seed(0)
    obs = [space.sample() for _ in range(8)]
    batch = {k: torch.as_tensor(np.stack([o[k] for o in obs])) for k in obs[0]}
    with torch.no_grad():
        assert not torch.allclose(fitted.mean_action(batch), first.mean_action(batch), atol=1e-3)  # a new fit, not SFT
    ev = shown(store, "evaluate", *sets)
    assert json.loads((ev / "metrics.json").read_text())["method"] == "rule_fbc"
    assert "Filtered BC in ManiSkill" in (ev / "report.md").read_text()
    # without the world-model figure evaluate reads no world model either: the whole run is ManiSkill's
    assert sorted(json.loads((ev / "manifest.json").read_text())["key_inputs"]["inputs"]) == ["collect", "rl", "sft", "tokenize"]
    assert not (ev / "extreme_actions.png").exists() and shown(store, "evaluate", *sets, "--set", "train_wm.dim=48") == ev


def test_filtered_bcs_controls_play_the_same_episodes_and_imitate_random_ones_or_none(store):
    base = ["--set", "rl.algorithm=filtered_bc", "--set", "rl.reward=wm", "--set", "rl.precision_envs=0",
            "--set", "rl.diagnostics=none"]
    runs = {}
    for name in ("success", "random", "none"):
        sets = [*base, "--set", f"rl.fbc_select={name}"]
        cli(store, "run", "--profile", "toy", "--until", "rl", *sets)
        runs[name] = shown(store, "rl", *sets)
    assert len(set(runs.values())) == 3
    assert [json.loads((runs[k] / "rl.json").read_text())["method"] for k in runs] == ["wm_fbc", "wm_fbc_random", "wm_fbc_none"]
    fields = ("t", "start", "length", "success", "env")
    played = {k: [{f: e[f] for f in fields} for e in json.loads((d / "episodes.json").read_text())] for k, d in runs.items()}
    assert played["success"] == played["random"] == played["none"] and played["success"]  # the same seed, the same play
    # play in the world model pays the done head's success alone (no frame decoded): a failure earns nothing
    episodes = json.loads((runs["success"] / "episodes.json").read_text())
    assert all(e["return"] == 0 for e in episodes if not e["success"])
    chosen, drawn, none = (json.loads((runs[k] / "filtered_bc.json").read_text())["rounds"][0] for k in runs)
    wins = sum(e["success"] for e in played["success"])
    assert chosen["picked_episodes"] == chosen["picked_successes"] == chosen["successes"] == wins
    assert chosen["own_pairs"] == sum(e["length"] for e in played["success"] if e["success"])
    assert drawn["select"] == "random" and drawn["picked_successes"] <= drawn["picked_episodes"]
    if wins:  # as many imagined steps as the successes hold; the last episode drawn may pass them (15 steps at most)
        assert chosen["own_pairs"] <= drawn["own_pairs"] < chosen["own_pairs"] + 15
    else:
        assert drawn["picked_episodes"] == drawn["own_pairs"] == 0
    # the refit alone: the same play and fit, nothing of its own imitated
    assert none["select"] == "none" and none["successes"] == wins
    assert none["picked_episodes"] == none["imitated_episodes"] == none["own_pairs"] == 0
    assert none["demonstration_pairs"] == chosen["demonstration_pairs"] and none["epochs"] == chosen["epochs"]
    # a success that must hold for 3 imagined steps: no episode ends as one sooner
    held = [*base, "--set", "rl.done_persist=3"]
    cli(store, "run", "--profile", "toy", "--until", "rl", *held)
    rl = shown(store, "rl", *held)
    assert json.loads((rl / "rl.json").read_text())["method"] == "wm_fbc_persist"
    ended = [e for e in json.loads((rl / "episodes.json").read_text()) if e["terminated"]]
    assert all(e["length"] >= 3 for e in ended)


def test_a_policy_reading_both_frames_plays_learns_in_the_world_model_and_is_evaluated(store):
    """``sft.frame=both``: the SFT policy, its play, filtered BC inside the world model (with the
    imagined-success check) and the evaluation all observe the frame now and the episode's first."""
    sets = ["--set", "sft.frame=both", "--set", "rl.algorithm=filtered_bc", "--set", "rl.reward=wm",
            "--set", "rl.diagnostics=none", "--set", "evaluate.world_model_figure=false"]
    acts = actions(cli(store, "run", "--profile", "toy", "--until", "evaluate", *sets))
    assert all(acts[(s, "ran")] == 1 for s in ("sft", "wm_play", "rl", "evaluate")), acts
    assert all(acts[(s, "cached")] == 1 for s in ("collect", "tokenize", "train_wm", "goals")), acts
    sft = shown(store, "sft", *sets)
    info = json.loads((sft / "policy.json").read_text())
    assert info["frame"] == "both" and json.loads((shown(store, "sft") / "policy.json").read_text())["frame"] == "current"
    from stages.sft.policy import POLICY_FILE, load_policy

    rl = shown(store, "rl", *sets)
    for path in (sft / POLICY_FILE, rl / "policy.zip"):  # the fine-tuned policy observes as its SFT start did
        assert load_policy(path).observation_space["codes"].shape[0] == 2 * info["bits"]
    metrics = json.loads((rl / "metrics.json").read_text())
    assert "imagined/ind/precision" in metrics and "imagined/ood/precision" in metrics
    results = [json.loads(x) for x in (shown(store, "evaluate", *sets) / "results.jsonl").read_text().splitlines()]
    assert {r["policy"] for r in results} >= {"sft", "ppo"} and {r["split"] for r in results} >= {"ind", "ood"}


def test_an_sft_ensemble_plays_is_fine_tuned_by_ppo_and_is_evaluated(store):
    """``sft.ensemble=2``: two SFT trainings kept as one network (their mean action), which wm_play's play,
    PPO in the world model and the evaluation take as they take one policy."""
    sets = ["--set", "sft.ensemble=2", "--set", "rl.diagnostics=none", "--set", "rl.precision_envs=0",
            "--set", "evaluate.world_model_figure=false"]
    acts = actions(cli(store, "run", "--profile", "toy", "--until", "evaluate", *sets))
    assert all(acts[(s, "ran")] == 1 for s in ("sft", "wm_play", "rl", "evaluate")), acts
    sft = shown(store, "sft", *sets)
    info = json.loads((sft / "policy.json").read_text())
    metrics = json.loads((sft / "metrics.json").read_text())
    assert info["ensemble"] == 2 and len(metrics["members"]) == 2
    from stages.sft.policy import POLICY_FILE, load_policy

    for path in (sft / POLICY_FILE, shown(store, "rl", *sets) / "policy.zip"):
        policy = load_policy(path)
        assert policy.members == 2 and len(policy.pi_features_extractor.members) == 2, path
    results = [json.loads(x) for x in (shown(store, "evaluate", *sets) / "results.jsonl").read_text().splitlines()]
    assert {r["policy"] for r in results} >= {"sft", "ppo"}


def test_dagger_adds_the_planners_continuations_from_the_policys_own_states(store):
    """The default ``sft.dagger_rounds=2``: the cloned policy acts on IND training environments, the planner
    finishes its failures from where it stopped, and the policy is trained again on both (stages.sft.dagger),
    twice; ``sft.dagger_rounds=0`` is the cloning alone."""
    plain_sets = ["--set", "sft.dagger_rounds=0"]
    acts = actions(cli(store, "run", "--profile", "toy", "--until", "sft", *plain_sets))
    assert acts[("sft", "ran")] == 1 and acts[("collect", "cached")] == 1, acts
    sft = shown(store, "sft")
    metrics = json.loads((sft / "metrics.json").read_text())
    every = [json.loads(x) for x in (sft / "dagger.jsonl").read_text().splitlines()]
    assert [r["round"] for r in every] == [1, 1, 2, 2]  # two rounds of two starts
    assert metrics["dagger/round1/starts"] == metrics["dagger/round2/starts"] == 2
    assert all(r["seed"] >= 6_000_000 for r in every)  # never an evaluation state
    assert len({r["seed"] for r in every}) == 4  # each round its own starts
    added = [r for r in every if r["takeover"] == "success"]
    assert len(added) == metrics["dagger/demonstrations"] >= 1 and all(r["pairs"] > 0 for r in added)
    rows = [r for r in every if r["round"] == 1]  # the round rolled out by the plain cloning
    assert {r["env_id"].split("/")[0] for r in rows} == {"move_to_aim", "pick_place"}  # round-robin over the tasks
    failed = [r for r in rows if not r["policy_success"]]
    assert failed and all(r["policy_steps"] <= 4 for r in every)  # an untrained toy policy, handed over at step 4 at most
    finished = [r for r in failed if r["takeover"] == "success"]
    assert metrics["pairs/train"] == metrics["pairs/train_collected"] + metrics["dagger/pairs"]
    assert metrics["dagger/pairs"] == sum(r["pairs"] for r in every)
    plain = json.loads((shown(store, "sft", *plain_sets) / "metrics.json").read_text())
    assert not (shown(store, "sft", *plain_sets) / "dagger.jsonl").exists()
    assert plain["pairs/train"] == metrics["pairs/train_collected"]  # the same collected demonstrations
    # rl's demonstration anchor and filtered BC read what SFT trained on: the continuations included
    from stages.collect.dataset import Dataset
    from stages.rl.demonstrations import sft_pairs
    from stages.sft import TEXT_EMBEDDINGS, read_policy_json
    from stages.sft.observation import ObservationFn
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer

    tok_dir, info = shown(store, "tokenize"), read_policy_json(sft)
    obs_fn = ObservationFn.for_policy(load_tokenizer(tok_dir), json.loads((sft / TEXT_EMBEDDINGS).read_text()), info)
    read = sft_pairs(sft, info, Dataset(shown(store, "collect")), TokenStore(tok_dir), obs_fn, "train")
    assert len(read[1]) == metrics["pairs/train"]
    # the round's starts reproduce from the plain SFT policy (the same first cloning), and are drawn
    out = subprocess.run([sys.executable, "scripts/dagger_strips.py", str(shown(store, "collect")), str(tok_dir), str(sft),
                          "--policy", str(shown(store, "sft", *plain_sets)), "--out", str(store.parent / "dagger_strips")],
                         cwd=REPO, capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert out.returncode == 0, out.stderr[-3000:]
    assert f"rows equal to dagger.jsonl in the policy's part: {len(failed)} of {len(failed)}" in out.stdout
    assert len(list((store.parent / "dagger_strips").glob("*_success.png"))) == len(finished)


def test_sft_killed_after_a_dagger_rounds_checkpoint_resumes_without_rolling_that_round_out_again(store):
    """Each DAgger round's demonstrations are a checkpoint: a run of two rounds killed (kill -9) once the
    first round's is published rolls out only the second round on its rerun (without cloning the
    demonstrations alone again), and the artifact holds the first round exactly as the killed run left it."""
    import signal
    import time

    sets = ["--set", "sft.dagger_rounds=2", "--set", "sft.seed=1"]  # two rounds, a key no other test commits
    args = ["run", "--profile", "toy", "--until", "sft", *sets, "--store", str(store)]
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", *args], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 900
    while not (marks := list((store / "partial" / "sft").glob("*/dagger-round-0/.checkpoint.json"))):
        assert proc.poll() is None, "sft ended before it was killed"
        assert time.time() < deadline
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    checkpoint = marks[0].parent
    assert not (checkpoint.parent / "dagger-round-1").exists()  # killed before the second round was saved
    kept_rows = (checkpoint / "rollouts.jsonl").read_text().splitlines()
    with np.load(checkpoint / "demos.npz") as z:
        kept = {k: z[k] for k in z.files}
    status = cli(store, "status", "--profile", "toy", "--until", "sft", *sets).stdout
    assert "resumes from checkpoints: dagger-round-0" in status

    cli(store, *args[:-2])
    sft = shown(store, "sft", *sets)
    log = (sft / "log.txt").read_text()
    assert "DAgger round 1 resumed from its checkpoint" in log and "DAgger round 2 resumed" not in log
    assert "the cloning on the demonstrations alone is skipped" in log  # only round 1's policy is trained again
    assert "DAgger round 2: the policy succeeded" in log  # rolled out by the rerun
    assert not list((store / "partial" / "sft").glob(f"{sft.name}*"))  # dropped at commit
    rows = [json.loads(x) for x in (sft / "dagger.jsonl").read_text().splitlines()]
    first = [{k: v for k, v in r.items() if k != "round"} for r in rows if r["round"] == 1]
    assert first == [json.loads(x) for x in kept_rows]  # the killed run's round, not a new one
    second = [r for r in rows if r["round"] == 2]
    assert len(second) == 2 and {r["seed"] for r in second}.isdisjoint({r["seed"] for r in first})
    metrics = json.loads((sft / "metrics.json").read_text())
    assert metrics["dagger/round1/starts"] == metrics["dagger/round2/starts"] == 2
    assert metrics["pairs/train"] == metrics["pairs/train_collected"] + sum(r["pairs"] for r in rows)
    assert len(kept) == 5 * sum(r["takeover"] == "success" for r in first)  # 5 arrays per demonstration
    with np.load(sft / "dagger_demos" / "demos.npz") as z:  # round 1's demonstrations first, as saved
        assert all(np.array_equal(z[k], v) for k, v in kept.items())


def test_branched_starts_lie_before_success_and_episodes_end_at_the_branch_horizon(store):
    from types import SimpleNamespace

    import numpy as np

    from stages.common.frame_skip import frame_indices
    from stages.common.proprio import proprio_from_state
    from stages.rl import Config
    from stages.rl.inputs import RLInputs

    ctx = SimpleNamespace(input=lambda name: artifact(store, name), device="cpu")
    inp = RLInputs.load(ctx, Config())
    envs = inp.training_envs(inp.tasks)
    first, every = inp.starts(envs), inp.starts(envs, any_frame=True)
    assert len(every) > len(first)
    env = next(e for e in envs if any(inp.meta[i].success and i in inp.split["train"] for i in e.episodes))
    eid = next(i for i in env.episodes if inp.meta[i].success and i in inp.split["train"])
    states = inp.dataset.load_states(eid)
    idx = frame_indices(len(states["action"]), inp.frame_skip)
    first_success = int(np.argmax(np.asarray(states["success"])[idx]))
    own = inp._starts_before_success(env, eid)
    assert len(own) == first_success > 0  # every frame before the first successful one, none after
    assert np.array_equal(own[0].tokens, inp.tokens(eid)[0]) and np.allclose(own[0].proprio, inp.first_proprio(eid))
    j = first_success - 1
    assert np.array_equal(own[j].tokens, inp.tokens(eid)[j])
    assert np.allclose(own[j].proprio, proprio_from_state(states["ee_pose"][idx[j]], states["qpos"][idx[j]])[0])

    cli(store, "run", "--profile", "toy", "--until", "rl", "--set", "rl.branch_horizon=3", "--set", "rl.precision_envs=0")
    rl = artifact(store, "rl")
    m = json.loads((rl / "metrics.json").read_text())
    assert m["ppo/start_states"] == len(every)
    episodes = json.loads((rl / "episodes.json").read_text())
    assert episodes and max(e["length"] for e in episodes) <= 3  # the toy profile's horizon is 15
    assert all(e["length"] == 3 for e in episodes if not e["terminated"])
    assert all(e["task"] and e["env"].startswith(e["task"] + "/") for e in episodes)  # where each episode ran


def test_imagined_bc_fine_tunes_the_policy_ppo_starts_from_and_saves_it(store):
    import torch

    from stages.sft.policy import POLICY_FILE, flat_params, load_policy

    cli(store, "run", "--profile", "toy", "--until", "rl", "--set", "rl.imagined_bc_epochs=2", "--set", "rl.precision_envs=0")
    rl = artifact(store, "rl")
    m = json.loads((rl / "metrics.json").read_text())
    assert m["imagined_bc/real_pairs"] > 0 and m["imagined_bc/imagined_pairs"] > 0
    assert m["imagined_bc/imagined_pairs"] < m["imagined_bc/real_pairs"]  # a demonstration's first frame has no twin
    adapted, sft = load_policy(rl / "imagined_bc_policy.zip"), load_policy(artifact(store, "sft") / POLICY_FILE)
    assert not torch.equal(flat_params(adapted), flat_params(sft))  # the start PPO got is not SFT's
    assert "rl: imagined BC" in (rl / "log.txt").read_text()


def test_the_calibration_gate_trains_ppo_on_the_tasks_it_keeps(store):
    fail = subprocess.run([sys.executable, "-m", "pipeline", "run", "--profile", "toy", "--until", "rl", "--store", str(store),
                           "--set", "rl.calibration_ratio=0.5", "--set", "rl.precision_envs=0"],
                          cwd=REPO, capture_output=True, text=True, timeout=3000)
    assert fail.returncode != 0 and "wm_play's play has no episode of tasks" in fail.stderr  # the toy play: 2 episodes, 4 tasks
    cli(store, "run", "--profile", "toy", "--until", "rl", "--set", "wm_play.episodes=4", "--set", "rl.calibration_ratio=0.5",
        "--set", "rl.precision_envs=0")
    rl = artifact(store, "rl")
    table = json.loads((rl / "calibration.json").read_text())
    rows = {r["task"]: r for r in table["tasks"]}
    assert table["ratio"] == 0.5 and set(rows) == {"pick_place", "push", "pull", "move_to_aim"}
    facts = json.loads((rl / "rl.json").read_text())
    assert facts["method"] == "wm_gated" and facts["calibration_ratio"] == 0.5  # its own rows in evaluate and sweep reports
    assert all(r["played"] == 1 and r["starts"] >= 1 for r in rows.values())
    m = json.loads((rl / "metrics.json").read_text())
    assert m["calibration/kept_tasks"] == sum(r["kept"] for r in rows.values())
    episodes = json.loads((rl / "episodes.json").read_text())
    if not m["calibration/kept_tasks"]:
        assert m["ppo/timesteps"] == 0 and not episodes  # PPO did not run: the policy is SFT's
    else:
        assert m["ppo/timesteps"] > 0 and episodes
    from types import SimpleNamespace

    from stages.rl import Config
    from stages.rl.inputs import RLInputs

    inp = RLInputs.load(SimpleNamespace(input=lambda name: artifact(store, name), device="cpu"), Config())
    kept = {t for t, r in rows.items() if r["kept"]}
    assert m["train_environments"] == len([e for e in inp.training_envs(inp.tasks) if e.task in kept])


def test_the_guard_refits_on_replayed_imagined_episodes(store):
    cli(store, "run", "--profile", "toy", "--until", "rl", "--set", "rl.guard=true", "--set", "rl.guard_replay_rounds=1",
        "--set", "rl.guard_replay_envs=2")
    rl = artifact(store, "rl")
    m = json.loads((rl / "metrics.json").read_text())
    assert m["guard/replay/rounds_done"] == 1 and m["guard/replay/round1/environments"] == 2
    assert m["guard/replay/frames"] > 0 and m["guard/replay/sim_policy_steps"] == m["guard/replay/frames"]
    assert (rl / "guard.pt").is_file()
    for split in ("ind", "ood"):  # precision counts what the guarded env counts: the guard can only veto
        assert m[f"imagined/{split}/imagined_done"] <= m[f"imagined/{split}/head_only/imagined_done"]
        for k in (5, 10):  # the frames' fidelity under the policy's actions (toy horizon 15), and a still scene's
            for name in ("token_accuracy", "copy_first_accuracy"):
                v = m[f"imagined/{split}/{name}_at_{k}"]
                assert v is None or 0.0 <= v <= 1.0
        rows = json.loads((rl / "imagined.json").read_text())[split]
        assert rows and all(1 <= len(r["token_accuracy"]) == len(r["copy_accuracy"]) for r in rows)


def test_the_world_model_is_fine_tuned_on_the_sft_policys_play(store):
    import torch

    from stages.train_wm.rollout import CHECKPOINTS, load_net

    play = shown(store, "wm_play")  # the fixture run's: the toy profile plays 2 episodes, fine-tunes 3 steps
    m = json.loads((play / "metrics.json").read_text())
    assert m["episodes"] == 2 and 0 <= m["successes"] <= 2
    assert 2 <= m["policy_steps"] <= 2 * 15  # at least one step each, at most the toy horizon
    assert m["train_episodes"] > 0 and m["finetune_seconds"] > 0
    rows = json.loads((play / "play.json").read_text())
    assert len(rows) == 2 and sum(r["success"] for r in rows) == m["successes"]
    tuned = load_net(play / CHECKPOINTS["action"]).state_dict()
    base = load_net(artifact(store, "train_wm") / CHECKPOINTS["action"]).state_dict()
    assert tuned.keys() == base.keys()
    assert any(not torch.equal(tuned[k], base[k]) for k in base)  # three steps moved it
    rl_inputs = json.loads((shown(store, "rl") / "manifest.json").read_text())["key_inputs"]["inputs"]
    assert rl_inputs["wm_play"] == play.name  # PPO trained in it


def test_wm_play_killed_during_its_fine_tune_resumes_from_its_play_and_matches_a_fresh_run(store):
    """The play and the fine-tune's state are checkpoints (pipeline.checkpoints): a run killed in the
    fine-tune, after a fine-tune checkpoint, plays no more on its rerun and resumes the fine-tune where
    it was saved, and the artifact equals one made from scratch (``--force``) at the same key."""
    import os
    import signal
    import time

    args = ["run", "--profile", "toy", "--until", "wm_play", "--set", "wm_play.steps=60", "--store", str(store)]
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", *args], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 600
    while not list((store / "partial" / "wm_play").glob("*/finetune/.checkpoint.json")):
        assert proc.poll() is None, "wm_play ended before it was killed (raise its steps)"
        assert time.time() < deadline
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    status = cli(store, "status", "--profile", "toy", "--until", "wm_play", "--set", "wm_play.steps=60").stdout
    assert "resumes from checkpoints: finetune, play" in status
    resumed = cli(store, *args[:-2])
    play = shown(store, "wm_play", "--set", "wm_play.steps=60")
    log = (play / "log.txt").read_text()
    assert "resumed from an earlier run's checkpoint" in log and "plays in ManiSkill" not in resumed.stderr
    assert re.search(r"play_wm resumed at step [1-9]\d*/60 from a checkpoint", log), log
    assert not list((store / "partial" / "wm_play").glob(f"{play.name}*"))  # dropped at commit
    digests = json.loads((play / "manifest.json").read_text())["files"]
    cli(store, *args[:-2], "--force", "wm_play")
    fresh = json.loads((play / "manifest.json").read_text())["files"]
    assert "resumed" not in (play / "log.txt").read_text()
    for f in ("action_wm.pt", "play.json"):
        assert digests[f]["blake3"] == fresh[f]["blake3"], f


def test_without_play_rl_trains_in_train_wms_model(store):
    acts = actions(cli(store, "run", "--profile", "toy", "--until", "rl", "--set", "wm_play.episodes=0"))
    assert acts[("wm_play", "ran")] == 1 and acts[("rl", "ran")] == 1 and acts[("sft", "cached")] == 1
    play = artifact(store, "wm_play")
    assert json.loads((play / "wm_play.json").read_text()) == {"finetuned": False, "episodes": 0}
    assert not (play / "action_wm.pt").exists()
    m = json.loads((artifact(store, "rl") / "metrics.json").read_text())
    assert "imagined/ind/imagined_done" in m  # the precision check ran, in train_wm's model


def test_the_scripts_imagine_in_a_world_model_checkpoint_they_are_given(store):
    """scripts/policy_check.py's ``wm_net`` (replay_imagined --wm-net): a checkpoint replaces train_wm's network,
    train_wm's proprioception head and decoding stay; it and a wm_play artifact cannot both be given."""
    import torch

    sys.path.insert(0, str(REPO / "scripts"))
    from policy_check import load_check

    from stages.sft.policy import POLICY_FILE

    ups = {s: shown(store, s) for s in ("collect", "tokenize", "train_wm", "sft", "wm_play")}
    args = (ups["collect"], ups["tokenize"], ups["train_wm"], ups["sft"], ups["sft"] / POLICY_FILE)
    plain = load_check(*args, split="ind", envs=1, steps=3)
    given = load_check(*args, split="ind", envs=1, steps=3, wm_net=ups["wm_play"] / "action_wm.pt")
    try:
        tuned = torch.load(ups["wm_play"] / "action_wm.pt", map_location="cpu", weights_only=True)["state_dict"]
        assert all(torch.equal(v, tuned[k]) for k, v in given.wm.net.state_dict().items())
        assert any(not torch.equal(v, plain.wm.net.state_dict()[k]) for k, v in tuned.items())  # a different network
        assert given.wm.proprio_head is not None and given.wm.decode_steps == plain.wm.decode_steps
    finally:
        plain.sim.close(), given.sim.close()
    with pytest.raises(SystemExit, match="give one"):
        load_check(*args, split="ind", envs=1, steps=3, wm_play=ups["wm_play"], wm_net=ups["wm_play"] / "action_wm.pt")
