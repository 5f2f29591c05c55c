"""The rl stage's work, in order: fit learned rewards, diagnose rewards, PPO from the SFT policy, save."""
from __future__ import annotations

import json
import time

import numpy as np
import torch

from stages.common.curves import Curves
from stages.common.precision import layout_of
from stages.rl.demo_bc import DemoBC
from stages.rl.diagnostics import binned_curve, plot_curves, progress_correlation
from stages.rl.guard import Guard, fit_done_ensemble
from stages.rl.ppo import make_ppo, normalized_rewards
from stages.rl.rewards import REGISTRY, GoalDistance, RewardParts, WMReward
from stages.rl.rewards.fit import fit_embedding_head, fit_proxy, frame_set
from stages.rl.self_imitation import SelfImitationRecorder
from stages.rl.success_only import SuccessOnly
from stages.rl.training import TrainingLog, plot_training, summary, write_episode_files
from stages.rl.wm_env import WorldModelVecEnv
from stages.sft.policy import flat_params

HEAD_FITS = {"embedding": fit_embedding_head, "proxy": fit_proxy}


def _episode_tuples(inp, ids: list[str]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    return [inp.steps(i) for i in ids]


def train(ctx, cfg, inp) -> dict:
    t_stage = time.perf_counter()
    tasks = inp.tasks
    chosen = REGISTRY[cfg.reward]
    metrics: dict = {}
    envs = inp.training_envs(tasks)
    ctx.log.info("rl: reward %s, %d training environments of tasks %s", cfg.reward, len(envs), tasks)
    ppo_envs = envs
    if cfg.imagined_bc_epochs:  # a world-model reward (the config's validator): the gate reads the adapted policy
        metrics.update(_imagined_bc(ctx, cfg, inp))
    if cfg.calibration_ratio:  # a world-model reward (the config's validator): PPO's tasks pass the gate
        ppo_envs = _calibration_gate(ctx, cfg, inp, envs, metrics)
    metrics["train_environments"] = len(ppo_envs)

    # ---- learned rewards (fitted to the rule reward of IND training episodes) ----------------------
    wanted = {"all": list(REGISTRY), "selected": [cfg.reward], "none": []}[cfg.diagnostics]
    parts = RewardParts()
    fits = sorted({REGISTRY[name].needs_head for name in wanted} - {None})
    guard = None
    if fits or cfg.guard:
        fit_ids = inp.episodes_for(inp.split["train"], tasks, False, cfg.head_episodes, cfg.seed)
        with ctx.progress(len(fit_ids), "rl: hidden states for reward heads", unit="ep") as bar:
            fs_fit = frame_set(inp.wm, _episode_tuples(inp, fit_ids), inp.device, bar)
        for head in fits:
            parts.heads[head], losses = HEAD_FITS[head](fs_fit, inp.tok, steps=cfg.head_steps, lr=cfg.head_lr, seed=cfg.seed,
                                                        device=inp.device)
            metrics[f"heads/{head}/final_mse"] = float(np.mean(losses[-20:]))
        metrics["heads/frames"] = int(len(fs_fit.reward))
        if cfg.guard and chosen.env == "wm":
            ensemble, losses = fit_done_ensemble(fs_fit.hidden, fs_fit.success, heads=cfg.guard_heads,
                                                 steps=cfg.guard_steps, lr=cfg.head_lr, seed=cfg.seed, device=inp.device)
            guard = Guard(ensemble, cfg.guard_coef, cfg.theta_done)
            metrics["guard/final_bce"] = float(np.mean(losses[-20:]))
            metrics["guard/positive_frames"] = int(fs_fit.success.sum())
            torch.save(_cpu_state(ensemble), ctx.out / "guard.pt")
        torch.save({k: _cpu_state(v) for k, v in parts.heads.items()}, ctx.out / "reward_heads.pt")

    if inp.goals is not None:
        goal_third, goal_wrist = inp.goal_frames()
        parts.distance = GoalDistance(goal_third, goal_wrist, inp.device, cfg.wm_dtype)  # LPIPS in the env's precision

    # ---- reward diagnostics on held-out successful episodes ------------------------------------------
    if wanted:
        metrics.update(_diagnose(ctx, cfg, inp, wanted, parts))

    # ---- the environment and its reward --------------------------------------------------------------
    payout_gamma = cfg.gamma if cfg.success_payout else None
    if chosen.env == "sim":
        raw_env = _sim_vec_env(ctx, cfg, inp, envs, payout_gamma)
    else:
        starts = inp.starts(ppo_envs or envs, any_frame=cfg.branch_horizon > 0)  # no task kept: never stepped
        metrics["ppo/start_states"] = len(starts)
        # filtered BC reads only which episodes the done head ends: its play pays the sparse term alone, so the
        # environment decodes no frame (the decoder costs about as much as the world model's step)
        paid = cfg.model_copy(update={"beta": 0.0}) if cfg.algorithm == "filtered_bc" else cfg
        raw_env = WorldModelVecEnv(inp.wm, inp.tok, inp.obs_fn, chosen.build(parts, paid, cfg.num_envs),
                                   starts, num_envs=cfg.num_envs, max_steps=cfg.branch_horizon or cfg.max_episode_steps,
                                   theta_done=cfg.theta_done, seed=cfg.seed, device=inp.device,
                                   payout_gamma=payout_gamma, guard=guard, dtype=cfg.wm_dtype,
                                   done_persist=cfg.done_persist)
    env = normalized_rewards(raw_env, cfg)
    refit = _guard_refit(ctx, cfg, inp, envs, raw_env, fs_fit) if guard is not None and cfg.guard_replay_rounds else None

    if cfg.algorithm == "filtered_bc":
        model = _filtered_bc(ctx, cfg, inp, raw_env, env, metrics)
        initial = {k: v.detach().clone() for k, v in inp.sft_policy.state_dict().items()}  # for the acceptance test
        env.close()
        return _after_training(ctx, cfg, inp, model, initial, raw_env, metrics, t_stage)

    # ---- PPO from the SFT policy -------------------------------------------------------------------
    model = make_ppo(env, cfg, inp.sft_policy, inp.sft_info, inp.device)
    if cfg.imagined_bc_epochs:  # the policy PPO starts from, for evaluation on its own
        model.save(ctx.out / "imagined_bc_policy.zip")
    if cfg.demo_bc_batches:
        model.demo_bc = DemoBC.from_sft(ctx.input("sft"), inp.sft_info, inp.dataset, inp.store, inp.obs_fn,
                                        batches=cfg.demo_bc_batches, batch_size=model.batch_size,
                                        coef=cfg.demo_bc_coef, seed=cfg.seed)
        metrics["demo_bc/pairs"] = len(model.demo_bc)
    before = flat_params(model.policy)
    initial = {k: v.detach().clone() for k, v in model.policy.state_dict().items()}  # SFT's weights, for the acceptance test

    t0 = time.perf_counter()
    with ctx.progress(cfg.total_timesteps, f"rl: PPO ({cfg.reward})", unit="step") as bar, Curves(ctx.out) as curves:
        log = TrainingLog(ctx.out, cfg.total_timesteps, cfg.snapshots, progress=bar, curves=curves)
        model.curves = curves
        callbacks = [log] if model.self_imitation is None else [log, SelfImitationRecorder(model.self_imitation)]
        if refit is not None:
            callbacks.append(refit)
        if ppo_envs:
            model.learn(total_timesteps=cfg.total_timesteps, callback=callbacks)
        else:
            ctx.log.warning("rl: the calibration gate kept no task: PPO does not run, the policy stays SFT's")
        model.curves = None
    seconds = time.perf_counter() - t0
    model.save(ctx.out / "policy.zip")
    log.write()
    env.close()
    after = flat_params(model.policy)
    plot_training(log.episodes, ctx.out / "training.png", f"PPO, reward={cfg.reward}", log.unfinished_from())
    metrics.update({f"ppo/{k}": v for k, v in log.summary().items()})
    metrics.update({
        "ppo/timesteps": int(model.num_timesteps), "ppo/seconds": seconds,
        "ppo/env_steps_per_second": model.num_timesteps / seconds if model.num_timesteps else 0.0,
        "ppo/param_change_relative": float((after - before).norm() / before.norm()),
        "ppo/updates": int(model.updates_done),
        "ppo/kl_to_sft_last": model.kl_history[-1] if model.kl_history else None,
    })
    if model.self_imitation is not None:
        metrics.update({f"self_imitation/{k}": v for k, v in model.self_imitation.last_stats.items()})
    if model.demo_bc is not None and model.demo_bc.last_stats:
        metrics["demo_bc/loss_last"] = model.demo_bc.last_stats["loss"]
    if refit is not None:
        metrics.update(refit.metrics())
        torch.save(_cpu_state(raw_env.guard.ensemble), ctx.out / "guard.pt")  # the last refit's ensemble
    if isinstance(raw_env, WorldModelVecEnv):
        metrics["ppo/clipped_action_entries"] = int(raw_env.roll.clip_count)
        metrics["ppo/wm_dtype"] = raw_env.dtype  # what "auto" resolved to on this machine
        if raw_env.reward.needs_frames:  # the layouts conv_layout timed faster here (stages.common.precision)
            metrics["ppo/decoder_layout"] = layout_of(raw_env.tok.net.decoder)
            if parts.distance is not None:
                metrics["ppo/lpips_layout"] = layout_of(parts.distance.net)
    ctx.log.info("rl: %s", {k: v for k, v in metrics.items() if k.startswith("ppo/")})
    return _after_training(ctx, cfg, inp, model, initial, raw_env, metrics, t_stage)


def _after_training(ctx, cfg, inp, model, initial: dict, raw_env, metrics: dict, t_stage: float) -> dict:
    """The acceptance test and the imagined-success check of the trained policy (either algorithm)."""
    if cfg.accept_episodes:
        metrics.update(_accept(ctx, cfg, inp, model, initial))
    if cfg.precision_envs:
        metrics.update(_imagined_precision(ctx, cfg, inp, model.policy, getattr(raw_env, "guard", None)))
    metrics["stage_seconds"] = time.perf_counter() - t_stage
    return metrics


def _filtered_bc(ctx, cfg, inp, raw_env, env, metrics: dict):
    """``fbc_rounds`` rounds of play in ``raw_env`` and the sft recipe on the demonstrations plus every
    success so far (``stages.rl.filtered_bc``); the last fit, as an SB3 model like PPO's (policy.zip)."""
    from stages.rl.filtered_bc import clone, demonstration_pairs, joined, play, random_like, sft_recipe

    recipe = sft_recipe(ctx.input("sft"))
    demos, val = demonstration_pairs(ctx.input("sft"), inp.sft_info, inp.dataset, inp.store, inp.obs_fn)
    policy, info = inp.sft_policy, inp.sft_info
    own, episodes, snapshots, rounds = [], [], [], []
    step, t0, unfinished_from = 0, time.perf_counter(), 0
    for k in range(cfg.fbc_rounds):
        budget = cfg.total_timesteps // cfg.fbc_rounds + (k < cfg.total_timesteps % cfg.fbc_rounds)
        policy.set_training_mode(False)
        with ctx.progress(budget, f"rl: filtered BC round {k + 1}/{cfg.fbc_rounds}, play ({cfg.reward})", unit="step") as bar:
            played = play(policy, raw_env, budget, seed=cfg.seed * 1000 + k, step0=step,
                          keep_failures=cfg.fbc_select == "random", progress=bar)
        unfinished_from = step + played.steps if k < cfg.fbc_rounds - 1 else played.budget_reached_at
        step += played.steps
        episodes += played.episodes
        picked = {"success": lambda: played.successes, "none": list,  # none: the refit alone, a control
                  "random": lambda: random_like(played, np.random.default_rng([cfg.seed, k]))}[cfg.fbc_select]()
        own += picked
        train = joined(demos, own)
        with ctx.progress(cfg.fbc_epochs, f"rl: filtered BC round {k + 1}/{cfg.fbc_rounds}, fit", unit="epoch") as bar:
            policy, info, fit = clone(recipe, inp.sft_info, inp.obs_fn.space, train, val, epochs=cfg.fbc_epochs,
                                      device=inp.device, progress=bar)
        wins = sum(e["success"] for e in played.episodes)
        rounds.append({"round": k, "env_steps": played.steps, "episodes": len(played.episodes), "successes": wins,
                       "select": cfg.fbc_select, "picked_episodes": len(picked),
                       "picked_successes": sum(any(p is s for s in played.successes) for p in picked),
                       "imitated_episodes": len(own), "demonstration_pairs": int(len(demos[1])),
                       "own_pairs": int(len(train[1]) - len(demos[1])), **fit})
        ctx.log.info("rl: filtered BC round %d: %d episodes, %d successes (%.2f); imitating %d episodes (%s, %d of "
                     "them successes); fit on %d demonstration + %d own pairs, held-out loss %.4f", k + 1,
                     len(played.episodes), wins, wins / max(1, len(played.episodes)), len(picked), cfg.fbc_select,
                     rounds[-1]["picked_successes"], len(demos[1]), rounds[-1]["own_pairs"],
                     fit["loss_val_last"] or float("nan"))
        model = make_ppo(env, cfg, policy, info, inp.device)  # the fit in PPO's format: evaluate reads one kind
        path = ctx.out / "snapshots" / f"step_{step:08d}.zip"
        path.parent.mkdir(parents=True, exist_ok=True)
        model.save(path)
        snapshots.append({"timesteps": step, "wall_seconds": time.perf_counter() - t0,
                          "path": str(path.relative_to(ctx.out))})
    seconds = time.perf_counter() - t0
    model.save(ctx.out / "policy.zip")
    write_episode_files(ctx.out, episodes, unfinished_from, snapshots)
    (ctx.out / "filtered_bc.json").write_text(json.dumps({"rounds": rounds}, indent=1) + "\n")
    plot_training(episodes, ctx.out / "training.png", f"filtered BC, reward={cfg.reward}", unfinished_from)
    metrics.update({f"ppo/{k}": v for k, v in summary(episodes, unfinished_from).items()})
    metrics.update({
        "ppo/timesteps": step, "ppo/seconds": seconds, "ppo/env_steps_per_second": step / seconds if seconds else 0.0,
        "filtered_bc/imitated_episodes": len(own), "filtered_bc/own_pairs": rounds[-1]["own_pairs"],
        "filtered_bc/loss_val_last": rounds[-1]["loss_val_last"], "filtered_bc/rounds": cfg.fbc_rounds,
    })
    if isinstance(raw_env, WorldModelVecEnv):
        metrics["ppo/wm_dtype"] = raw_env.dtype
    ctx.log.info("rl: %s", {k: v for k, v in metrics.items() if k.startswith(("ppo/", "filtered_bc/"))})
    return model


def _accept(ctx, cfg, inp, model, initial: dict) -> dict:
    """The acceptance test (stages.rl.acceptance); when SFT wins, policy.zip is re-saved with SFT's weights."""
    from stages.rl.acceptance import acceptance_test

    result, rows = acceptance_test(ctx, cfg, inp, ctx.out)
    (ctx.out / "acceptance.json").write_text(json.dumps(result, indent=1) + "\n")
    (ctx.out / "acceptance_episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    d = result["difference"]
    name = "PPO" if cfg.algorithm == "ppo" else "filtered BC"  # acceptance.json's "ppo": the rl stage's policy, either
    ctx.log.info("rl: acceptance test on %d IND validation states: SFT %.3f, %s %.3f, %s minus SFT %+.3f [%+.3f, %+.3f] "
                 "(margin %+.2f): keeping %s", d["n"], result["sft_success"], name, result["ppo_success"], name, d["diff"],
                 d["lo"], d["hi"], cfg.accept_margin, f"the {name} policy" if result["kept"] == "ppo" else "the SFT policy")
    if result["kept"] == "sft":
        model.policy.load_state_dict(initial)
        model.save(ctx.out / "policy.zip")
    return {"accept/episodes": result["episodes"], "accept/seconds": result["seconds"],
            "accept/sft_success": result["sft_success"], "accept/ppo_success": result["ppo_success"],
            "accept/difference": d["diff"], "accept/difference_lo": d["lo"], "accept/difference_hi": d["hi"],
            "accept/kept_ppo": result["kept"] == "ppo"}


def _imagined_bc(ctx, cfg, inp) -> dict:
    """Fine-tune ``inp.sft_policy`` in place on the sft stage's demonstrations and their imagined twins
    (``stages.rl.imagined_bc``); PPO saves it as ``imagined_bc_policy.zip`` before it learns. Returns its metrics: pair counts and
    the held-out loss on real and on imagined pairs before and after."""
    from stages.rl.demonstrations import sft_demos
    from stages.rl.imagined_bc import imagined_pairs, joined
    from stages.sft.data import pairs
    from stages.sft.policy import behaviour_clone, evaluate_pairs

    t0 = time.perf_counter()
    weights = torch.as_tensor(inp.sft_info["demonstrations"]["loss_weights"], dtype=torch.float32)
    sets = {}
    for part in ("train", "val"):
        demos = sft_demos(ctx.input("sft"), inp.sft_info, inp.dataset, inp.store, part)
        if not demos:
            continue
        with ctx.progress(1, f"rl: imagined BC, imagining the {part} demonstrations", unit="set") as bar:
            sets[part] = (pairs(demos, inp.obs_fn), imagined_pairs(inp.wm, inp.obs_fn, demos, cfg.imagined_bc_horizon))
            bar.update(1)
    if "train" not in sets:
        raise ValueError(f"imagined BC: {ctx.input('sft')}/split.json lists no training demonstrations")
    policy = inp.sft_policy
    out = {"imagined_bc/real_pairs": int(len(sets["train"][0][1])), "imagined_bc/imagined_pairs": int(len(sets["train"][1][1]))}

    def held_out(when: str) -> None:
        if "val" in sets:
            for name, pr in zip(("real", "imagined"), sets["val"]):
                out[f"imagined_bc/val_loss_{name}_{when}"] = evaluate_pairs(policy, pr, weights)["loss"]

    held_out("before")
    val = joined(*sets["val"]) if "val" in sets else None
    with ctx.progress(cfg.imagined_bc_epochs, "rl: imagined BC, epochs", unit="epoch") as bar:
        behaviour_clone(policy, joined(*sets["train"]), val, epochs=cfg.imagined_bc_epochs, lr=cfg.imagined_bc_lr,
                        weight_decay=0.0, batch_size=256, patience=cfg.imagined_bc_epochs, weights=weights,
                        seed=cfg.seed, keep="last", progress=bar)
    held_out("after")
    out["imagined_bc/seconds"] = time.perf_counter() - t0
    ctx.log.info("rl: imagined BC: %s", out)
    return out


def _calibration_gate(ctx, cfg, inp, envs: list, metrics: dict) -> list:
    """The training environments of the tasks that pass the calibration gate (stages.rl.calibration);
    its table goes to ``calibration.json`` and ``metrics``."""
    from stages.rl.calibration import calibrate
    from stages.wm_play import PLAY_JSON

    play = json.loads((ctx.input("wm_play") / PLAY_JSON).read_text())
    by_task = {t: inp.starts([e for e in envs if e.task == t]) for t in inp.tasks}
    with ctx.progress(len(by_task), "rl: calibration gate (SFT policy imagined per task)", unit="task") as bar:
        table = calibrate(inp.sft_policy, inp.wm, inp.obs_fn, by_task, play, cfg.max_episode_steps, cfg.theta_done,
                          cfg.calibration_starts, cfg.seed, progress=bar, persist=cfg.done_persist)
    rows = [c.row(cfg.calibration_ratio) for c in table]
    (ctx.out / "calibration.json").write_text(json.dumps({"ratio": cfg.calibration_ratio, "tasks": rows}, indent=1) + "\n")
    for r in rows:
        for k in ("imagined_rate", "real_rate", "kept"):
            metrics[f"calibration/{r['task']}/{k}"] = r[k]
    kept = [r["task"] for r in rows if r["kept"]]
    metrics["calibration/kept_tasks"] = len(kept)
    ctx.log.info("rl: calibration gate (ratio %g): %s; PPO trains on %s", cfg.calibration_ratio,
                 {r["task"]: f"imagined {r['imagined']}/{r['starts']}, real {r['real']}/{r['played']}" for r in rows},
                 kept or "no task")
    return [e for e in envs if e.task in kept]


def replay_sim(ctx, cfg, inp, picked: list):
    """(ManiSkill env over the picked environments, rendering and controlling as collect did, their specs)."""
    from stages.common.sim_env import sim_over

    return sim_over(ctx.input("collect"), inp.obs_fn, picked, max_steps=cfg.max_episode_steps,
                    frame_skip=inp.frame_skip, seed=cfg.seed)


def _guard_refit(ctx, cfg, inp, envs: list, raw_env, fs_fit):
    """The callback that refits the guard on replayed imagined episodes of IND training environments."""
    from stages.rl.guard_refit import SEED_BASE, GuardRefit
    from stages.common.environments import pick_environments
    from stages.rl.imagined import imagine_and_replay

    picked = pick_environments(envs, cfg.guard_replay_envs)

    def imagine(policy, k: int):
        policy.set_training_mode(False)  # PPO's next update switches it back
        sim, specs = replay_sim(ctx, cfg, inp, picked)
        seeds = [SEED_BASE + 100_000 * cfg.seed + 1000 * k + i for i in range(len(specs))]
        record: dict = {}
        try:
            rows = imagine_and_replay(policy, inp.wm, inp.tok, inp.obs_fn, sim, specs, seeds, cfg.max_episode_steps,
                                      cfg.theta_done, record=record, guard=raw_env.guard,  # the guard in place now
                                      persist=cfg.done_persist)
        finally:
            sim.close()
        return rows, record["hidden"]

    return GuardRefit(raw_env, imagine, fs_fit.hidden, fs_fit.success, total_timesteps=cfg.total_timesteps,
                      rounds=cfg.guard_replay_rounds, heads=cfg.guard_heads, steps=cfg.guard_steps, lr=cfg.head_lr,
                      seed=cfg.seed, coef=cfg.guard_coef, theta=cfg.theta_done, device=inp.device, log=ctx.log)


def _cpu_state(module: torch.nn.Module) -> dict:
    """A module's state dict on the CPU: artifacts load the same whatever device trained them."""
    return {k: v.detach().cpu() for k, v in module.state_dict().items()}


def _imagined_precision(ctx, cfg, inp, policy, guard=None) -> dict:
    """The final policy imagines episodes from fresh simulator starts; ManiSkill replays them. With the
    env's ``guard`` an imagined success needs its confirmation, as in training; the done head alone is
    reported beside it (``imagined/<split>/head_only/...``)."""
    from stages.common.environments import pick_environments
    from stages.rl.imagined import (PERSIST_STEPS, STRICTER_THETAS, TCP_ERROR_STEPS, imagine_and_replay,
                                    precision_at, precision_head_only, precision_metrics, tcp_error_at,
                                    token_accuracy_at)

    policy.set_training_mode(False)
    out, table = {}, {}
    for split in ("ind", "ood"):
        picked = pick_environments([e for e in inp.envs if e.split == split and e.task in inp.tasks], cfg.precision_envs)
        if not picked:
            continue
        sim, specs = replay_sim(ctx, cfg, inp, picked)
        seeds = [3_000_000 + 1000 * cfg.seed + i for i in range(len(specs))]  # apart from training and evaluation
        try:
            with ctx.progress(len(specs), f"rl: imagined vs replayed ({split})", unit="env") as bar:
                rows = imagine_and_replay(policy, inp.wm, inp.tok, inp.obs_fn, sim, specs, seeds,
                                          cfg.max_episode_steps, cfg.theta_done, guard=guard, persist=cfg.done_persist)
                bar.update(len(specs))
        finally:
            sim.close()
        table[split] = [vars(r) for r in rows]
        out.update({f"imagined/{split}/{k}": v for k, v in precision_metrics(rows).items()})
        if guard is not None:  # what the done head alone would have counted
            out.update({f"imagined/{split}/head_only/{k}": v for k, v in precision_head_only(rows, cfg.theta_done, cfg.done_persist).items()})
        for theta in (t for t in STRICTER_THETAS if t > cfg.theta_done):  # what a stricter done threshold would give
            m = precision_at(rows, theta, persist=cfg.done_persist)
            out[f"imagined/{split}/imagined_done_at_{theta:g}"] = m["imagined_done"]
            out[f"imagined/{split}/precision_at_{theta:g}"] = m["precision"]
        for k in PERSIST_STEPS:  # what a success held for k imagined steps would give
            m = precision_at(rows, cfg.theta_done, persist=k)
            out[f"imagined/{split}/imagined_done_persist_{k}"] = m["imagined_done"]
            out[f"imagined/{split}/precision_persist_{k}"] = m["precision"]
        for k, err in tcp_error_at(rows, TCP_ERROR_STEPS).items():  # the arm's fidelity under the policy's actions
            out[f"imagined/{split}/tcp_error_cm_at_{k}"] = None if err is None else 100 * err
        for k, acc in token_accuracy_at(rows, TCP_ERROR_STEPS).items():  # the frames' fidelity, and a still scene's
            out[f"imagined/{split}/token_accuracy_at_{k}"], out[f"imagined/{split}/copy_first_accuracy_at_{k}"] = acc or (None, None)
    (ctx.out / "imagined.json").write_text(json.dumps(table, indent=1) + "\n")
    ctx.log.info("rl: imagined-success precision %s", {k: v for k, v in out.items() if k.endswith(("precision", "done"))})
    return out


def _diagnose(ctx, cfg, inp, wanted: list[str], parts: RewardParts) -> dict:
    """Every wanted module's reward along held-out successful episodes, computed by the module itself."""
    out: dict = {}
    curves: dict[str, dict[str, np.ndarray]] = {}
    for split, ids in (("ind", inp.split["heldout"]), ("ood", inp.split["ood"])):
        pick = inp.episodes_for(ids, inp.tasks, True, cfg.diagnostics_episodes, cfg.seed)
        if not pick:
            ctx.log.warning("rl: no successful held-out %s episodes for reward diagnostics", split)
            continue
        with ctx.progress(len(pick), f"rl: diagnostics {split}", unit="ep") as bar:
            fs = frame_set(inp.wm, _episode_tuples(inp, pick), inp.device, bar)
        decoded, first_decoded = inp.tok.decode(fs.tokens), inp.tok.decode(fs.first_tokens)
        goal_rows = np.array([inp.env_of(pick[e]) for e in fs.episode])
        modules = {name: REGISTRY[name].build(parts, cfg, 1) for name in wanted}
        if "wm" in modules:  # its two terms on their own as well
            w = modules["wm"]
            modules["wm_dense"] = WMReward(parts.distance, alpha=0.0, beta=1.0, theta_sps=w.theta, dense=w.dense_kind,
                                           gamma=w.gamma)
            modules["wm_sparse"] = WMReward(parts.distance, alpha=1.0, beta=0.0, theta_sps=w.theta)
        rewards = {name: np.zeros(len(fs.episode)) for name in modules}
        for e in range(len(pick)):
            first, frames = fs.episode_batches(e, decoded, first_decoded, goal_rows)
            for name, module in modules.items():
                rewards[name][fs.episode == e] = module.along(first, frames)
        out[f"diagnostics/{split}/episodes"] = len(pick)
        curves[split] = {}
        for name, r in rewards.items():
            out[f"diagnostics/{split}/{name}/spearman_progress"] = progress_correlation(r, fs.progress, fs.episode)
            curves[split][name] = binned_curve(r, fs.progress)
    if curves:
        plot_curves(curves, ctx.out / "reward_diagnostics.png")
    return out


def _sim_vec_env(ctx, cfg, inp, envs, payout_gamma: float | None):
    """``sim_envs`` simulator envs over the training environments (the ``rule`` baseline)."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    from stages.collect.catalog import read_scenes_json
    from stages.collect.dataset import read_sim_facts
    from stages.common.sim_env import SimSpec, SimTaskEnv

    scenes = read_scenes_json(ctx.input("collect") / "scenes.json")
    facts = read_sim_facts(ctx.input("collect"))  # render and control as the demonstrations were recorded
    specs = [SimSpec(e.task, scenes[e.scene_id].to_dict(), e.instruction, inp.goal_index.get(e.env_id, -1)) for e in envs]
    n = min(cfg.sim_envs, len(specs))
    groups = [specs[i::n] for i in range(n)]

    def make(g, i):
        env = SimTaskEnv(g, inp.obs_fn, max_steps=cfg.max_episode_steps, seed=cfg.seed + i, action_repeat=inp.frame_skip,
                         image_size=facts.image_size, robot_mesh=facts.robot_mesh, payout_gamma=payout_gamma)
        return SuccessOnly(env) if cfg.rule_terms == "success" else env

    return DummyVecEnv([lambda g=g, i=i: make(g, i) for i, g in enumerate(groups)])
