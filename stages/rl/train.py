"""The rl stage's work, in order: fit learned rewards, diagnose rewards, PPO from the SFT policy, save."""
from __future__ import annotations

import time

import numpy as np
import torch

from stages.rl.diagnostics import binned_curve, plot_curves, progress_correlation
from stages.rl.ppo import make_ppo
from stages.rl.rewards import EmbeddingReward, GoalDistance, ProxyReward, WMReward
from stages.rl.rewards.fit import FrameSet, fit_embedding_head, fit_proxy, frame_set
from stages.rl.training import TrainingLog, plot_training
from stages.rl.wm_env import WorldModelVecEnv
from stages.sft.policy import flat_params


def _episode_tuples(inp, ids: list[str]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    return [inp.steps(i) for i in ids]


def _frames(inp, fs: FrameSet) -> tuple[torch.Tensor, torch.Tensor]:
    return inp.tok.decode(fs.tokens)


def train(ctx, cfg, inp) -> dict:
    t_stage = time.perf_counter()
    tasks = inp.tasks
    metrics: dict = {"reward": cfg.reward, "tasks": tasks, "frame_skip": inp.frame_skip}
    envs = inp.training_envs(tasks)
    metrics["train_environments"] = len(envs)
    ctx.log.info("rl: reward %s, %d training environments of tasks %s", cfg.reward, len(envs), tasks)

    # ---- learned rewards (fitted to the rule reward of IND training episodes) ----------------------
    wanted = {"wm", "rule", "embedding", "proxy"} if cfg.diagnostics == "all" else {cfg.reward}
    heads = {}
    if wanted & {"embedding", "proxy"}:
        fit_ids = inp.episodes_for(inp.split["train"], tasks, False, cfg.head_episodes, cfg.seed)
        with ctx.progress(len(fit_ids), "rl: hidden states for reward heads", unit="ep") as bar:
            fs_fit = frame_set(inp.wm, _episode_tuples(inp, fit_ids), inp.device, bar)
        if "embedding" in wanted:
            heads["embedding"], losses = fit_embedding_head(fs_fit, steps=cfg.head_steps, lr=cfg.head_lr, seed=cfg.seed)
            metrics["heads/embedding/final_mse"] = float(np.mean(losses[-20:]))
        if "proxy" in wanted:
            heads["proxy"], losses = fit_proxy(fs_fit, inp.tok, steps=cfg.head_steps, lr=cfg.head_lr, seed=cfg.seed)
            metrics["heads/proxy/final_mse"] = float(np.mean(losses[-20:]))
        metrics["heads/frames"] = int(len(fs_fit.reward))
        torch.save({k: v.state_dict() for k, v in heads.items()}, ctx.out / "reward_heads.pt")

    goal_third, goal_wrist = inp.goal_frames()
    distance = GoalDistance(goal_third, goal_wrist, inp.device)

    # ---- reward diagnostics on held-out successful episodes ------------------------------------------
    metrics.update(_diagnose(ctx, cfg, inp, wanted, heads, distance))

    # ---- the environment and its reward --------------------------------------------------------------
    if cfg.reward == "rule":
        env = _sim_vec_env(ctx, cfg, inp, envs)
    else:
        module = {
            "wm": lambda: WMReward(distance, alpha=cfg.alpha, beta=cfg.beta, theta_sps=cfg.theta_sps, dense=cfg.dense,
                                   gamma=cfg.gamma, num_envs=cfg.num_envs),
            "embedding": lambda: EmbeddingReward(heads["embedding"]),
            "proxy": lambda: ProxyReward(heads["proxy"]),
        }[cfg.reward]()
        env = WorldModelVecEnv(inp.wm, inp.tok, inp.obs_fn, module, inp.starts(envs), num_envs=cfg.num_envs,
                               max_steps=cfg.max_episode_steps, theta_done=cfg.theta_done, seed=cfg.seed,
                               device=inp.device)

    # ---- PPO from the SFT policy -------------------------------------------------------------------
    model = make_ppo(env, cfg, inp.sft_policy, inp.sft_info, inp.device)
    before = flat_params(model.policy)

    log = TrainingLog(ctx.out, cfg.total_timesteps, cfg.snapshots)
    t0 = time.perf_counter()
    with ctx.progress(cfg.total_timesteps, f"rl: PPO ({cfg.reward})", unit="step") as bar:
        log.progress = bar
        model.learn(total_timesteps=cfg.total_timesteps, callback=log)
    seconds = time.perf_counter() - t0
    model.save(ctx.out / "policy.zip")
    log.write()
    env.close()
    after = flat_params(model.policy)
    plot_training(log.episodes, ctx.out / "training.png", f"PPO, reward={cfg.reward}")
    metrics.update({f"ppo/{k}": v for k, v in log.summary().items()})
    metrics.update({
        "ppo/timesteps": int(model.num_timesteps), "ppo/seconds": seconds,
        "ppo/env_steps_per_second": model.num_timesteps / seconds,
        "ppo/param_change_relative": float((after - before).norm() / before.norm()),
        "stage_seconds": time.perf_counter() - t_stage,
    })
    if isinstance(env, WorldModelVecEnv):
        metrics["ppo/clipped_action_entries"] = int(env.roll.clip_count)
    ctx.log.info("rl: %s", {k: v for k, v in metrics.items() if k.startswith("ppo/")})
    return metrics


def _diagnose(ctx, cfg, inp, wanted: set[str], heads: dict, distance: GoalDistance) -> dict:
    out: dict = {}
    curves: dict[str, dict[str, np.ndarray]] = {}
    for split, ids in (("ind", inp.split["heldout"]), ("ood", inp.split["ood"])):
        pick = inp.episodes_for(ids, inp.tasks, True, cfg.diagnostics_episodes, cfg.seed)
        if not pick:
            ctx.log.warning("rl: no successful held-out %s episodes for reward diagnostics", split)
            continue
        with ctx.progress(len(pick), f"rl: diagnostics {split}", unit="ep") as bar:
            fs = frame_set(inp.wm, _episode_tuples(inp, pick), inp.device, bar)
        third, wrist = _frames(inp, fs)
        goal_rows = np.array([inp.env_of(pick[e]) for e in fs.episode])
        rewards = {}
        if "rule" in wanted:
            rewards["rule"] = fs.reward.numpy().astype(np.float64)
        if "wm" in wanted:
            sim = 1.0 - distance(third, wrist, goal_rows)
            sparse = (fs.done_prob.numpy() >= cfg.theta_sps).astype(np.float64)
            rewards["wm"] = cfg.alpha * sparse + cfg.beta * sim
            rewards["wm_dense"] = sim
            rewards["wm_sparse"] = sparse
        with torch.no_grad():
            if "embedding" in heads:
                rewards["embedding"] = heads["embedding"](fs.hidden).numpy().astype(np.float64)
            if "proxy" in heads:
                rewards["proxy"] = heads["proxy"](third, wrist).numpy().astype(np.float64)
        out[f"diagnostics/{split}/episodes"] = len(pick)
        curves[split] = {}
        for name, r in rewards.items():
            out[f"diagnostics/{split}/{name}/spearman_progress"] = progress_correlation(r, fs.progress, fs.episode)
            curves[split][name] = binned_curve(r, fs.progress)
    if curves:
        plot_curves(curves, ctx.out / "reward_diagnostics.png")
    return out


def _sim_vec_env(ctx, cfg, inp, envs):
    """``sim_envs`` simulator envs over the training environments (the ``rule`` baseline)."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    from stages.collect.catalog import read_scenes_json
    from stages.collect.dataset import read_sim_facts
    from stages.rl.sim_env import SimSpec, SimTaskEnv

    scenes = read_scenes_json(ctx.input("collect") / "scenes.json")
    facts = read_sim_facts(ctx.input("collect"))  # render and control as the demonstrations were recorded
    specs = [SimSpec(e.task, scenes[e.scene_id].to_dict(), e.instruction, inp.goal_index[e.env_id]) for e in envs]
    n = min(cfg.sim_envs, len(specs))
    groups = [specs[i::n] for i in range(n)]
    return DummyVecEnv([lambda g=g, i=i: SimTaskEnv(g, inp.obs_fn, max_steps=cfg.max_episode_steps, seed=cfg.seed + i,
                                                      action_repeat=inp.frame_skip, image_size=facts.image_size,
                                                      robot_mesh=facts.robot_mesh)
                        for i, g in enumerate(groups)])
