"""sft: behaviour cloning of one multi-task policy on the collected demonstrations (the paper's
"Supervised Finetune" row and the starting point of every RL method).

Its own stage so that every point of a reward sweep reuses one SFT policy per (seed, tasks): the
rl stage only fine-tunes it. Recipe (docs/sft.md, with the ablation behind each choice): the
optimal demonstrations re-timed so that no step starts from rest (``data.py``), per-dimension action
normalisation inside the network (``policy.TaskPolicy``) with the three near-noise rotation dims
down-weighted, the gripper as an open / close decision executed by its sign, dropout on the image
features, a held-out split of demonstrations with early stopping, AdamW with a cosine schedule,
PPO's initial action noise set per dimension from the held-out residuals, then two DAgger rounds with
the planner as the expert (``dagger.py``: the planner's continuations from where the cloned policy
stopped, trained on with the demonstrations; the first round +0.13 success at ``small``, docs/RESULTS.md
prediction 20, the second about +0.03 more, out of domain, prediction 25).

Inputs:
    collect -- demonstrations (states, actions, instructions; only successful episodes are used)
    tokenize -- frame tokens (the visual part of the observation), the tokenizer, its IND train split

Outputs:
    sft_policy.pt        the behaviour-cloned policy (``stages.sft.policy.load_policy``)
    policy.json          what the policy is and needs: frame_skip, tasks, observation layout (and which frame), noise,
                         how its demonstrations were read and weighed (rl.demo_bc_batches reuses it)
    text_embeddings.json MiniLM embedding of every instruction of the collect artifact
    split.json           demonstration episodes trained on and held out (early stopping, R^2)
    training.png         train / held-out loss per epoch (also as TensorBoard events in tensorboard/)
    metrics.json         pairs, epochs, best epoch, held-out loss, per-dimension R^2 and residual std
    dagger.jsonl, dagger_demos/   with ``dagger_rounds``: every DAgger start, and the planner's continuations
                         trained on beside split.json's demonstrations (``stages.sft.dagger``)

Key includes:
    this config (tasks, kinds, frame skip, recipe, seed) and the keys of collect and tokenize.
    Not the reward, not any PPO setting: a reward sweep shares one sft artifact per seed.

Toy profile:
    a few epochs on the toy demonstrations (seconds).
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

from stages.collect.plans import RECOVERY_KINDS, SUBOPTIMAL_KINDS
from stages.common.curves import Curves
from stages.collect.tasks import TASKS, Task

POLICY_JSON = "policy.json"
TEXT_EMBEDDINGS = "text_embeddings.json"
DAGGER_DIR = "dagger_demos"  # the DAgger rounds' demonstrations (stages.sft.dagger.save_demos), trained on beside split.json's


class Config(BaseModel):
    """sft stage configuration (defaults sized for the ``small`` profile)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, description="seed of initialisation, the held-out split and batch order")
    threads: int = Field(2, ge=1, description="torch CPU threads (ignored on CUDA); in the key: on a CPU the count "
                         "changes the floating-point reductions, so the weights (docs/rl.md, 'The thread count is "
                         "part of the result')")
    tasks: list[Task] = Field(
        list(TASKS), min_length=1, description="tasks the one policy is cloned on (multi-task when several)")
    kinds: list[Literal[("optimal", *SUBOPTIMAL_KINDS, *RECOVERY_KINDS)]] = Field(
        ["optimal"], min_length=1, description="trajectory kinds used as demonstrations (successful ones only; "
        "with the suboptimal kinds too, success fell: docs/sft.md; 'recover' needs collect.recover_per_scene > 0)")
    frame_skip: int = Field(4, ge=1, description="control steps per policy step; must equal train_wm.frame_skip (rl checks)")
    retime_min_move: float = Field(0.03, ge=0, description="re-time demonstrations: each kept step moves the TCP at "
                                   "least this far (m), 0 = every frame_skip-th frame (stages/sft/data.py)")
    retime_max_gap: int = Field(12, ge=1, description="re-timing: at most this many control steps between kept frames")
    data_fraction: float = Field(1.0, gt=0, le=1, description="fraction of the demonstration episodes used (learning curves)")
    val_fraction: float = Field(0.1, ge=0, lt=1, description="demonstration episodes held out for early stopping and R^2")
    epochs: int = Field(150, ge=0, description="maximum epochs (0 = an untrained policy)")
    patience: int = Field(20, ge=1, description="stop after this many epochs without a better held-out loss")
    keep: Literal["best", "last"] = Field("best", description="weights kept: the best held-out epoch (early stopping) "
                                          "or the last epoch (no early stopping)")
    lr: float = Field(1e-3, gt=0, description="peak AdamW learning rate (cosine decay to 0 over `epochs`)")
    weight_decay: float = Field(0.01, ge=0)
    batch_size: int = Field(256, ge=1)
    gripper_weight: float = Field(1.0, ge=0, description="weight of the gripper dimension in the normalised loss")
    rotation_weight: float = Field(0.1, ge=0, description="weight of the three rotation dimensions in the normalised loss "
                                   "(and in early stopping)")
    dropout: float = Field(0.3, ge=0, lt=1, description="dropout on the flattened image features")
    features_dim: int = Field(256, ge=8, description="width of the observation features")
    net_arch: int = Field(256, ge=8, description="width of the two hidden layers of the actor and of the critic")
    use_proprio: bool = Field(True, description="the policy reads proprioception (False: the ablation without it)")
    frame: Literal["current", "first", "both"] = Field(
        "current", description="whose tokens the policy reads: the frame now, the episode's first (real) frame, or both "
        "(stages/sft/observation.py; docs/sft.md)")
    normalize_actions: bool = Field(True, description="per-dimension action normalisation in the loss and network "
                                    "(False: raw actions, where the +-1 gripper dominates the MSE)")
    ensemble: int = Field(1, ge=1, description="policies trained on the same split, each from its own initialisation "
                          "and batch order; the stage keeps one network acting on their mean action "
                          "(stages.sft.policy.assemble; docs/sft.md, 'An ensemble of trainings')")
    dagger_rounds: int = Field(2, ge=0, description="DAgger rounds with the planner as the expert (stages/sft/dagger.py; "
                               "docs/sft.md): the policy acts on IND training environments, the planner finishes its "
                               "failures from where it stopped, and the policy is trained again on the demonstrations "
                               "plus those continuations; 0 = off (default 2 since prediction 25, 1 since prediction 20, "
                               "docs/RESULTS.md)")
    dagger_episodes: int = Field(256, ge=1, description="policy rollouts per DAgger round, round-robin over the tasks' "
                                 "IND training environments")
    dagger_max_steps: int = Field(75, ge=1, description="policy steps of a DAgger rollout before the planner takes over")
    dagger_plan_steps: int = Field(400, ge=1, description="control steps the planner's continuation may take")
    noise_scale: float = Field(1.0, gt=0, description="PPO's initial action std = noise_scale x held-out residual std")
    noise_floor: float = Field(0.02, gt=0, description="lower bound of the initial action std (action units)")

    @model_validator(mode="after")
    def _unique(self) -> "Config":
        if len(set(self.tasks)) != len(self.tasks):
            raise ValueError(f"tasks repeat: {self.tasks}")
        return self


def read_policy_json(sft_dir: str | Path) -> dict:
    """The sft artifact's ``policy.json`` (frame_skip, tasks, observation layout), with a clear error."""
    path = Path(sft_dir) / POLICY_JSON
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: is {sft_dir} a committed sft artifact?")
    return json.loads(path.read_text())


def run(ctx) -> None:
    from stages.collect.dataset import Dataset
    from stages.common.text_encoder import encode_texts
    from stages.sft.data import load_demo, pairs
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import (POLICY_FILE, assemble, behaviour_clone, dim_weights, evaluate_pairs, make_policy,
                                   member_seed, policy_kwargs)
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer

    cfg: Config = ctx.config
    t0 = time.perf_counter()
    if ctx.device == "cpu":
        torch.set_num_threads(cfg.threads)
    ds, store = Dataset(ctx.input("collect")), TokenStore(ctx.input("tokenize"))
    tok = load_tokenizer(ctx.input("tokenize"), ctx.device)
    instructions = sorted({m.instruction for m in ds.episodes})
    text = {s: e.tolist() for s, e in zip(instructions, encode_texts(instructions))}
    (ctx.out / TEXT_EMBEDDINGS).write_text(json.dumps(text) + "\n")
    obs_fn = ObservationFn(tok, text, cfg.frame)

    pool = set(json.loads((ctx.input("tokenize") / "split.json").read_text())["train"])
    ids = sorted(m.episode_id for m in ds.episodes
                 if m.episode_id in pool and m.success and m.task in cfg.tasks and m.kind in cfg.kinds)
    if not ids:
        raise ValueError(f"no successful IND training demonstrations of tasks {cfg.tasks} and kinds {cfg.kinds} "
                         f"in {ctx.input('collect')}")
    rng = np.random.default_rng(cfg.seed)
    order = [ids[i] for i in rng.permutation(len(ids))]
    n_val = int(round(cfg.val_fraction * len(order))) if len(order) > 1 else 0
    val_ids, train_ids = sorted(order[:n_val]), order[n_val:]
    train_ids = sorted(train_ids[: max(1, int(round(cfg.data_fraction * len(train_ids))))])
    (ctx.out / "split.json").write_text(json.dumps({"train": train_ids, "val": val_ids}, indent=1) + "\n")

    with ctx.progress(len(train_ids) + len(val_ids), "sft: demonstrations", unit="ep") as bar:
        demos = {}
        for i in train_ids + val_ids:
            demos[i] = load_demo(ds, store, i, cfg.frame_skip, cfg.retime_min_move, max(cfg.retime_max_gap, cfg.frame_skip))
            bar.update(1)
    train = pairs([demos[i] for i in train_ids], obs_fn)
    val = pairs([demos[i] for i in val_ids], obs_fn) if val_ids else None
    weights = dim_weights(cfg.gripper_weight, cfg.rotation_weight)
    ctx.log.info("sft: %d train / %d held-out demonstrations (%d / %d pairs), tasks %s, kinds %s",
                 len(train_ids), len(val_ids), len(train[1]), 0 if val is None else len(val[1]), cfg.tasks, cfg.kinds)

    def fit(train: tuple, label: str):
        """(policy, kwargs, member 0's history, the members' held-out scores, seconds) trained on ``train``."""
        if cfg.normalize_actions:
            loc, scale = train[1].mean(0), np.maximum(train[1].std(0), 1e-3)
        else:
            loc, scale = np.zeros(7, np.float32), np.ones(7, np.float32)
        kwargs = policy_kwargs(loc, scale, features_dim=cfg.features_dim, net_arch=cfg.net_arch,
                               use_proprio=cfg.use_proprio, dropout=cfg.dropout)
        t_fit = time.perf_counter()
        members, hists, member_held = [], [], []
        for k in range(cfg.ensemble):  # member 0 is the policy a run without an ensemble trains
            policy = make_policy(obs_fn.space, kwargs, cfg.lr).to(ctx.device)  # initialised from the run's RNG, in turn
            desc = f"sft{label}: epochs" if cfg.ensemble == 1 else f"sft{label}: member {k + 1}/{cfg.ensemble}, epochs"
            with ctx.progress(cfg.epochs, desc, unit="epoch") as bar:
                hists.append(behaviour_clone(policy, train, val, epochs=cfg.epochs, lr=cfg.lr,
                                             weight_decay=cfg.weight_decay, batch_size=cfg.batch_size,
                                             patience=cfg.patience, weights=weights, seed=member_seed(cfg.seed, k),
                                             keep=cfg.keep, progress=bar))
            members.append(policy)
            if cfg.ensemble > 1:
                member_held.append(evaluate_pairs(policy, val if val is not None else train, weights))
        if cfg.ensemble > 1:
            kwargs = policy_kwargs(loc, scale, features_dim=cfg.features_dim, net_arch=cfg.net_arch,
                                   use_proprio=cfg.use_proprio, dropout=cfg.dropout, members=cfg.ensemble)
            policy = assemble(members, obs_fn.space, kwargs)
        return policy, kwargs, hists, member_held, time.perf_counter() - t_fit

    dagger_metrics: dict = {}
    if cfg.dagger_rounds and ctx.checkpoints().load("dagger-round-0") is not None:
        # resumed past round 1's rollouts: the plain cloning they were rolled out by is not needed again
        ctx.log.info("sft: DAgger round 1's checkpoint found: the cloning on the demonstrations alone is skipped")
        plain = None
    else:
        plain = fit(train, "")
        policy, kwargs, hists, member_held, fit_seconds = plain
    if cfg.dagger_rounds:
        policy, kwargs, hists, member_held, fit_seconds, train, dagger_metrics = _dagger(
            ctx, cfg, plain, fit, train, obs_fn, pool)
    hist = hists[0]
    loc, scale = np.asarray(kwargs["action_loc"], np.float32), np.asarray(kwargs["action_scale"], np.float32)
    held = evaluate_pairs(policy, val if val is not None else train, weights)
    train_eval = evaluate_pairs(policy, train, weights)
    noise = np.maximum(cfg.noise_scale * np.asarray(held["residual_std"]), cfg.noise_floor)
    with torch.no_grad():
        policy.log_std.copy_(torch.as_tensor(np.log(noise), dtype=torch.float32))
    policy.save(str(ctx.out / POLICY_FILE))
    _plot(hist, ctx.out / "training.png")
    with Curves(ctx.out) as curves:  # per epoch, as in training.png
        curves.series("sft/loss_train", hist["train"])
        curves.series("sft/loss_heldout", hist["val"])

    info = {"frame_skip": cfg.frame_skip, "tasks": list(cfg.tasks), "observation": sorted(obs_fn.space.spaces),
            "frame": cfg.frame, "ensemble": cfg.ensemble,
            "grid": list(tok.grid), "bits": tok.bits, "action_loc": loc.tolist(), "action_scale": scale.tolist(),
            "initial_action_std": noise.tolist(),
            # how the demonstrations were read and weighed: rl's demonstration anchor (rl.demo_bc_batches) reuses it
            "demonstrations": {"retime_min_move": cfg.retime_min_move, "retime_max_gap": max(cfg.retime_max_gap, cfg.frame_skip),
                               "loss_weights": weights.tolist()},
            "policy_kwargs": {k: v for k, v in kwargs.items() if k != "features_extractor_class"}}
    (ctx.out / POLICY_JSON).write_text(json.dumps(info, indent=1) + "\n")
    dims = ["dx", "dy", "dz", "rx", "ry", "rz", "gripper"]
    metrics = {
        "demonstrations/train": len(train_ids), "demonstrations/val": len(val_ids),
        "pairs/train": int(len(train[1])), "pairs/val": 0 if val is None else int(len(val[1])),
        "epochs_run": hist["epochs_run"], "best_epoch": hist["best_epoch"],
        "loss/train_first": hist["train"][0] if hist["train"] else None,
        "loss/train_last": hist["train"][-1] if hist["train"] else None,
        "loss/val_best": min(hist["val"]) if hist["val"] else None,
        "loss_history": {"train": hist["train"], "val": hist["val"]},
        "val/loss": held["loss"],  # the kept policy's (the ensemble's, with members; the history is member 0's)
        "val/gripper_sign_accuracy": held["gripper_sign_accuracy"],
        "train/gripper_sign_accuracy": train_eval["gripper_sign_accuracy"],
        **{f"val/r2/{d}": v for d, v in zip(dims, held["r2"])},
        **{f"train/r2/{d}": v for d, v in zip(dims, train_eval["r2"])},
        **{f"val/residual_std/{d}": v for d, v in zip(dims, held["residual_std"])},
        "fit_seconds": fit_seconds, "stage_seconds": time.perf_counter() - t0,
    }
    metrics.update(dagger_metrics)
    if cfg.ensemble > 1:  # the members alone on the same held-out pairs, and their epochs
        metrics["members"] = [{"epochs_run": h["epochs_run"], "best_epoch": h["best_epoch"],
                               "val/loss": m["loss"], "val/gripper_sign_accuracy": m["gripper_sign_accuracy"],
                               **{f"val/r2/{d}": v for d, v in zip(dims, m["r2"])}}
                              for h, m in zip(hists, member_held)]
    ctx.write_metrics(metrics)
    ctx.log.info("sft: %d epochs (best %d) in %.0f s; held-out R^2 %s, gripper sign accuracy %.3f",
                 hist["epochs_run"], hist["best_epoch"], fit_seconds,
                 [round(v, 3) for v in held["r2"]], held["gripper_sign_accuracy"])


def _dagger(ctx, cfg: Config, plain: tuple | None, fit, train: tuple, obs_fn, pool: set):
    """``cfg.dagger_rounds`` rounds of ``stages.sft.dagger`` from ``plain``, ``fit``'s results on the
    demonstrations alone (None when round 1's checkpoint exists: nothing rolls out with it); each
    round's demonstrations are a checkpoint (a rerun after a kill rolls out again only the rounds it
    lacks, and trains no policy that only a checkpointed round rolled out) and ``dagger.jsonl`` lists
    every start. Returns ``fit``'s results for the last round's training set, that set, and the metrics."""
    from stages.common.environments import pick_environments, training_environments
    from stages.common.sim_env import sim_over
    from stages.goals.environments import list_environments
    from stages.sft.dagger import load_round, round_seeds, run_round, save_demos, save_round, summary

    envs = pick_environments(training_environments(list_environments(ctx.input("collect")), pool, cfg.tasks),
                             cfg.dagger_episodes)
    cp = ctx.checkpoints()
    added, rows_all, metrics = [], [], {}
    fitted = plain if plain is not None else (None,)
    for r in range(cfg.dagger_rounds):
        saved = cp.load(f"dagger-round-{r}")
        if saved is not None:
            demos, rows = load_round(saved)
            ctx.log.info("sft: DAgger round %d resumed from its checkpoint (%d demonstrations)", r + 1, len(demos))
        else:
            if fitted[0] is None:  # resumed past round r - 1's rollouts: train its policy again
                torch.manual_seed(_round_seed(cfg.seed, r))
                fitted = fit(_union(train, added, obs_fn), f" DAgger {r}")
            sim, specs = sim_over(ctx.input("collect"), obs_fn, envs, max_steps=cfg.dagger_max_steps,
                                  frame_skip=cfg.frame_skip, seed=cfg.seed)
            try:
                with ctx.progress(len(specs), f"sft: DAgger round {r + 1}/{cfg.dagger_rounds}", unit="ep") as bar:
                    demos, rows = run_round(fitted[0], sim, specs, round_seeds(cfg.seed, r, len(specs)),
                                            max_steps=cfg.dagger_max_steps, plan_steps=cfg.dagger_plan_steps,
                                            frame_skip=cfg.frame_skip, min_move=cfg.retime_min_move,
                                            max_gap=max(cfg.retime_max_gap, cfg.frame_skip), progress=bar)
            finally:
                sim.close()
            with cp.save(f"dagger-round-{r}") as d:
                save_round(d, demos, rows)
        added += demos
        rows_all += [(r, row) for row in rows]
        counts = summary(rows)
        metrics.update({f"dagger/round{r + 1}/{k}": v for k, v in counts.items()})
        ctx.log.info("sft: DAgger round %d: the policy succeeded in %d of %d starts; of its failures %d came to rest, "
                     "the planner finished %d (%d failed, %d without a plan): %d demonstrations, %d pairs", r + 1,
                     counts["policy_success"], counts["starts"], counts["rested"], counts["takeover_success"],
                     counts["takeover_failed"], counts["takeover_no_plan"], len(demos), counts["pairs"])
        fitted = (None,)  # round r + 1 needs the policy trained on the union so far
        union = _union(train, added, obs_fn)
        if r == cfg.dagger_rounds - 1 or cp.load(f"dagger-round-{r + 1}") is None:
            torch.manual_seed(_round_seed(cfg.seed, r + 1))
            fitted = fit(union, f" DAgger {r + 1}")
    from dataclasses import asdict

    (ctx.out / "dagger.jsonl").write_text("".join(json.dumps({"round": r + 1, **asdict(row)}) + "\n"
                                                  for r, row in rows_all))
    (ctx.out / DAGGER_DIR).mkdir()
    save_demos(ctx.out / DAGGER_DIR, added)  # trained on: rl's demonstration anchor reads them (stages.rl.demonstrations)
    metrics.update({"dagger/demonstrations": len(added), "dagger/pairs": int(sum(len(d.actions) for d in added)),
                    "pairs/train_collected": int(len(train[1]))})
    return (*fitted, union, metrics)


def _round_seed(seed: int, r: int) -> int:
    """The torch seed the policy trained after DAgger round ``r`` is initialised from (not the run's
    RNG, which the simulator may have drawn from)."""
    return int(np.random.SeedSequence([seed, 7_000 + r]).generate_state(1)[0])


def _union(train: tuple, demos: list, obs_fn) -> tuple:
    """The collected training pairs plus those of ``demos``."""
    from stages.sft.data import pairs

    if not demos:
        return train
    extra = pairs(demos, obs_fn)
    return {k: np.concatenate([train[0][k], extra[0][k]]) for k in train[0]}, np.concatenate([train[1], extra[1]])


def _plot(hist: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3))
    ax.plot(range(1, len(hist["train"]) + 1), hist["train"], label="train")
    if hist["val"]:
        ax.plot(range(1, len(hist["val"]) + 1), hist["val"], label="held-out demonstrations")
        ax.axvline(hist["best_epoch"], color="grey", ls=":", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("normalised action MSE")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


__all__ = ["Config", "run", "read_policy_json", "POLICY_JSON", "TEXT_EMBEDDINGS", "DAGGER_DIR"]
