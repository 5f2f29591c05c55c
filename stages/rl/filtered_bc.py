"""Filtered behaviour cloning (``rl.algorithm: filtered_bc``): the policy plays, its successes join the
demonstrations, the sft stage's recipe is rerun.

The SFT policy samples actions with its own noise (as PPO's first rollout does) in the rl stage's
environment for ``total_timesteps`` steps; every episode that environment calls a success becomes a
demonstration (its observations and executed actions, at policy steps); the sft stage's recipe
(``stages.sft.policy.behaviour_clone``, its network, loss weights, held-out demonstrations and seed)
is rerun from a fresh network on the demonstrations plus those episodes, for ``fbc_epochs`` epochs
kept at the last one (early stopping on the demonstrations' held-out loss stopped these fits at
epochs 9-22 and lost to SFT: docs/RESULTS.md). With a 0/1 episode reward this is reward-weighted
regression, one step of policy improvement; failed episodes are never imitated. With
``fbc_rounds`` k > 1 the budget is split in k rounds and each round's player is the previous
round's fit, each fit on the demonstrations and every success so far.

What counts as a success is the environment's: in ManiSkill (``reward: rule``) the simulator's
success check; in the world model (``reward: wm``) the done head's termination, so the policy also
imitates the episodes the done head wrongly calls successes (``imagined/<split>/precision``).

``fbc_select: random`` is the control that says what the selection adds: the same play, but the
imitated episodes are drawn at random from all those played, whatever their outcome, until they
hold as many steps as the round's successes (``random_like``): as much own data, no selection.
``fbc_select: none`` is the control that says what the refit itself does: the same play (recorded, never
imitated) and the same fit, on the demonstrations alone.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from stages.rl.training import episode_outcome, task_of
from stages.sft.policy import act


@dataclass
class Played:
    """What one round of play recorded."""

    episodes: list[dict] = field(default_factory=list)  # TrainingLog's fields: t, start, wall, return, length, ...
    successes: list[tuple[dict, np.ndarray]] = field(default_factory=list)  # (obs key -> (T, ...), actions (T, 7))
    failures: list[tuple[dict, np.ndarray]] = field(default_factory=list)  # the same, with keep_failures only
    steps: int = 0  # env steps taken (every env's), including those that finished the last episodes
    budget_reached_at: int = 0  # the step every recorded episode started before


def play(policy, env, budget: int, *, seed: int, step0: int = 0, keep_failures: bool = False,
         progress=None) -> Played:
    """Episodes of ``policy`` with sampled actions in the VecEnv ``env`` until ``budget`` env steps (summed
    over its envs) have been taken; the episodes running then are played to their end and no new one is
    recorded (so short successful episodes are not over-counted at the cut). Steps are numbered from
    ``step0``. The successful episodes' steps are kept, and the failed ones' with ``keep_failures``."""
    torch.manual_seed(seed)
    n = env.num_envs
    obs = env.reset()  # key -> (n, ...)
    buffers: list[list[tuple[dict, np.ndarray]]] = [[] for _ in range(n)]
    ret, start = np.zeros(n), np.full(n, step0, dtype=np.int64)
    recording = np.ones(n, dtype=bool)  # False: this env's episode began after the budget, not recorded
    out, reported = Played(), 0
    t0 = time.perf_counter()
    while recording.any():
        actions = act(policy, obs, deterministic=False)  # (n, 7) executed
        for i in np.nonzero(recording)[0]:
            buffers[i].append(({k: np.array(v[i]) for k, v in obs.items()}, actions[i]))
        obs, rewards, dones, infos = env.step(actions)
        out.steps += n
        ret += rewards
        now = step0 + out.steps
        for i in np.nonzero(dones)[0]:
            if recording[i]:
                terminated, success = episode_outcome(infos[i])
                env_key = infos[i].get("env", "")
                out.episodes.append({"t": now, "start": int(start[i]), "wall": time.perf_counter() - t0,
                                     "return": float(ret[i]), "length": len(buffers[i]), "terminated": terminated,
                                     "success": success, "env": env_key, "task": task_of(env_key)})
                if success or keep_failures:
                    steps_obs, steps_act = zip(*buffers[i])
                    (out.successes if success else out.failures).append(
                        ({k: np.stack([o[k] for o in steps_obs]) for k in steps_obs[0]},
                         np.stack(steps_act).astype(np.float32)))
            buffers[i], ret[i], start[i] = [], 0.0, now
            recording[i] = out.steps < budget
        if progress is not None and min(out.steps, budget) > reported:
            progress.update(min(out.steps, budget) - reported)
            reported = min(out.steps, budget)
        if out.steps >= budget and not out.budget_reached_at:
            out.budget_reached_at = now
    return out


def random_like(played: Played, rng: np.random.Generator) -> list[tuple[dict, np.ndarray]]:
    """``fbc_select: random``: played episodes (successful or not) in a random order, taken while they hold
    fewer steps than the successes do (the last one taken may pass that count); none without a success."""
    target = sum(len(a) for _, a in played.successes)
    pool = played.successes + played.failures
    picked, steps = [], 0
    for i in rng.permutation(len(pool)):
        if steps >= target:
            break
        picked.append(pool[i])
        steps += len(pool[i][1])
    return picked


def sft_recipe(sft_dir: Path):
    """The sft artifact's config (``stages.sft.Config``), read from its manifest: the recipe rerun here."""
    from stages.sft import Config

    path = Path(sft_dir) / "manifest.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: filtered BC reruns the sft recipe that built {sft_dir}, "
                                "and its manifest records it")
    return Config(**json.loads(path.read_text())["key_inputs"]["config"])


def demonstration_pairs(sft_dir: Path, sft_info: dict, dataset, store, obs_fn) -> tuple[tuple, tuple | None]:
    """The sft artifact's training and held-out demonstration pairs (``stages.rl.demonstrations``)."""
    from stages.rl.demonstrations import sft_pairs

    train = sft_pairs(sft_dir, sft_info, dataset, store, obs_fn, "train")
    if train is None:
        raise ValueError(f"filtered BC: {sft_dir}/split.json lists no training demonstrations")
    return train, sft_pairs(sft_dir, sft_info, dataset, store, obs_fn, "val")


def joined(demos: tuple[dict, np.ndarray], own: list[tuple[dict, np.ndarray]]) -> tuple[dict, np.ndarray]:
    """The demonstration pairs followed by every step of the own successful episodes."""
    obs, actions = demos
    if not own:
        return obs, actions
    return ({k: np.concatenate([obs[k], *[o[k].astype(obs[k].dtype) for o, _ in own]]) for k in obs},
            np.concatenate([actions, *[a for _, a in own]]).astype(np.float32))


def clone(recipe, sft_info: dict, observation_space, train: tuple[dict, np.ndarray], val: tuple | None, *,
          epochs: int, device: str, keep: str = "last", init=None, progress=None):
    """The sft recipe (``recipe``: a ``stages.sft.Config``) on ``train`` (held-out ``val``) from a fresh
    network, or from ``init`` (a policy whose action normalisation is kept), for ``epochs`` epochs,
    kept at the last one (``keep="best"``: the recipe's early stopping).

    Returns (policy, policy.json facts for it, fit facts). A fresh network normalises actions on
    ``train``; the action noise is set from the held-out residuals, as the sft stage does."""
    from stages.sft.policy import behaviour_clone, evaluate_pairs, make_policy, policy_kwargs

    torch.manual_seed(recipe.seed)  # the fresh network and dropout: the same whatever ran before in this process
    if init is None:
        loc, scale = train[1].mean(0), np.maximum(train[1].std(0), 1e-3)
        kwargs = policy_kwargs(loc, scale, features_dim=recipe.features_dim, net_arch=recipe.net_arch,
                               use_proprio=recipe.use_proprio, dropout=recipe.dropout)
        policy = make_policy(observation_space, kwargs, recipe.lr).to(device)
        kwargs = {k: v for k, v in kwargs.items() if k != "features_extractor_class"}
    else:
        policy, kwargs = init, sft_info["policy_kwargs"]
        loc, scale = np.asarray(sft_info["action_loc"], np.float32), np.asarray(sft_info["action_scale"], np.float32)
    weights = torch.as_tensor(sft_info["demonstrations"]["loss_weights"], dtype=torch.float32)
    t0 = time.perf_counter()
    hist = behaviour_clone(policy, train, val, epochs=epochs, lr=recipe.lr, weight_decay=recipe.weight_decay,
                           batch_size=recipe.batch_size, patience=recipe.patience, weights=weights, seed=recipe.seed,
                           keep=keep, progress=progress)
    held = evaluate_pairs(policy, val if val is not None else train, weights)
    noise = np.maximum(recipe.noise_scale * np.asarray(held["residual_std"]), recipe.noise_floor)
    with torch.no_grad():
        policy.log_std.copy_(torch.as_tensor(np.log(noise), dtype=torch.float32))
    info = {**sft_info, "action_loc": np.asarray(loc).tolist(), "action_scale": np.asarray(scale).tolist(),
            "initial_action_std": noise.tolist(), "policy_kwargs": kwargs,
            "ensemble": policy.members}  # a fresh network is one policy whatever the SFT artifact's ensemble
    facts = {"epochs": hist["epochs_run"], "loss_val_last": hist["val"][-1] if hist["val"] else None,
             "loss_val_best": min(hist["val"]) if hist["val"] else None, "best_epoch": hist["best_epoch"],
             "val_r2": held["r2"], "fit_seconds": time.perf_counter() - t0}
    return policy, info, facts


__all__ = ["Played", "play", "random_like", "sft_recipe", "demonstration_pairs", "joined", "clone"]
