"""wm_play: the action world model fine-tuned on the SFT policy's own play in ManiSkill.

Every collected episode is planner-made (optimal, perturbed, near-miss), so the world model has never
watched a learned policy act: under the policy's actions it imagines demonstration-like progress that
does not happen, and most imagined successes are not real (docs/RESULTS.md). Here the SFT policy
plays ``episodes`` episodes in ManiSkill on the IND training environments (round-robin over tasks,
deterministic actions, failures kept), recorded at the world model's step, and a copy of the action
world model is fine-tuned on its training episodes plus the play (listed ``weight`` times) with
train_wm's own losses and batch size. The rl stage trains PPO in the copy (and fits its reward heads,
diagnoses rewards and checks imagined-success precision in it). Like the guard's replays this spends
simulator steps before PPO, on training environments only: a departure from the paper's
simulator-free training. ``episodes: 0`` turns it off: the artifact then says so and the rl stage
uses train_wm's model as it is.

A stage of its own, not a step inside rl, because it depends on train_wm and sft only: every reward
point of a sweep shares one fine-tuned model per seed (``sft.seed+wm_play.seed+rl.seed`` in the
``rewards`` sweep).

Inputs:
    collect -- scenes (the simulator), episodes (the world model's training data)
    tokenize -- the tokenizer (the observation function) and the token store
    train_wm -- the action world model with its proprioception head, text embeddings, split, and
    its training config (read from its manifest: window, batch size, losses)
    sft -- the policy that plays, its tasks and frame skip (``policy.json``)

Outputs:
    wm_play.json        the fact rl reads through ``action_world_model``: whether the model was
                        fine-tuned, on how many play episodes
    action_wm.pt        the fine-tuned action world model (train_wm's checkpoint format); absent
                        with ``episodes: 0``
    play.json           every play episode: environment, seed, policy steps, success
    metrics.json        play episodes, successes, policy steps, seconds; the fine-tune's final losses

Key includes:
    this config and the keys of collect, tokenize, train_wm and sft.

Checkpoints (``ctx.checkpoints()``, pipeline.checkpoints):
    ``play``, the play once finished: a run killed during the fine-tune plays no more;
    ``finetune``, the fine-tune's whole training state (train_wm's format), saved every twelfth of
    its steps and after the last: a run killed during the fine-tune resumes at the last saved step and
    commits what an uninterrupted run commits.

Threads (CPU): the play runs on one torch thread (a policy step is a batch of one, the simulator is
serial), the fine-tune on ``threads`` (default 2, in the key, not the cores the executor gave this node,
so a key gives the same weights in a single run and in a sweep wave): its batches use both cores of a
2-core machine (docs/rl.md, "wm_play").

Toy profile:
    two play episodes of at most 15 steps and three fine-tuning steps: the real path, tiny.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from pydantic import BaseModel, ConfigDict, Field

WM_PLAY_JSON = "wm_play.json"
PLAY_JSON = "play.json"


class Config(BaseModel):
    """wm_play stage configuration (defaults sized for the ``small`` profile)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, description="play seeds are 5,000,000 + 1,000 x seed + i (apart from training, "
                                     "evaluation and the precision check)")
    episodes: int = Field(384, ge=0, description="episodes the SFT policy plays in ManiSkill; 0 = off (rl uses "
                                                 "train_wm's action world model unchanged)")
    max_episode_steps: int = Field(75, ge=1, description="policy steps per play episode at most (rl's horizon)")
    steps: int = Field(2000, ge=1, description="fine-tuning steps of the action world model")
    lr: float = Field(3e-4, gt=0, description="their peak learning rate (train_wm's schedule)")
    weight: int = Field(2, ge=1, description="times each play episode is listed beside the training episodes")
    threads: int = Field(2, ge=1, description="torch CPU threads of the fine-tune (ignored on CUDA); in the key: on a "
                         "CPU the count changes the floating-point reductions, so the weights (docs/rl.md, 'The "
                         "thread count is part of the result')")


def run(ctx) -> None:
    cfg: Config = ctx.config
    if ctx.device == "cpu":
        torch.set_num_threads(1)
    if not cfg.episodes:
        (ctx.out / WM_PLAY_JSON).write_text(json.dumps({"finetuned": False, "episodes": 0}) + "\n")
        (ctx.out / PLAY_JSON).write_text("[]\n")
        ctx.log.info("wm_play: episodes 0, the action world model stays train_wm's")
        ctx.write_metrics({"episodes": 0})
        return
    metrics = _play_and_finetune(ctx, cfg)
    (ctx.out / WM_PLAY_JSON).write_text(json.dumps({"finetuned": True, "episodes": cfg.episodes}) + "\n")
    ctx.write_metrics(metrics)


def _play_and_finetune(ctx, cfg: Config) -> dict:
    from stages.goals.environments import list_environments
    from stages.common.environments import pick_environments, training_environments
    from stages.common.sim_env import sim_over
    from stages.sft import read_policy_json
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, load_policy
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.common.training_state import save_every, training_checkpoint
    from stages.train_wm.data import load_episodes
    from stages.train_wm.rollout import CHECKPOINTS, TEXT_EMBEDDINGS, load_world_model, save_world_model
    from stages.wm_play.play import PLAY_SEED, finetune_on_play, load_play, play_episodes, save_play

    wm_dir = ctx.input("train_wm")
    wm = load_world_model(wm_dir, kind="action", device=ctx.device)
    sft_info = read_policy_json(ctx.input("sft"))
    if int(sft_info["frame_skip"]) != wm.spec.frame_skip:
        raise ValueError(f"sft.frame_skip ({sft_info['frame_skip']}) != train_wm.frame_skip ({wm.spec.frame_skip}): "
                         "a policy step must mean the same number of control steps in both; set them equal")
    split = json.loads((wm_dir / "split.json").read_text())
    envs = training_environments(list_environments(ctx.input("collect")), split["train"], list(sft_info["tasks"]))
    picked = pick_environments(envs, cfg.episodes)
    seeds = [PLAY_SEED + 1000 * cfg.seed + i for i in range(len(picked))]
    checkpoints = ctx.checkpoints()  # the play is kept if the run is killed during the fine-tune
    saved = checkpoints.load("play")
    if saved is not None:
        play = load_play(saved)
        t_play = json.loads((saved / "seconds.json").read_text())
        ctx.log.info("wm_play: the play (%d episodes, %.0f s) resumed from an earlier run's checkpoint", len(play), t_play)
    else:
        obs_fn = ObservationFn.for_policy(load_tokenizer(ctx.input("tokenize"), ctx.device),
                                          json.loads((wm_dir / TEXT_EMBEDDINGS).read_text()), sft_info)
        sim, specs = sim_over(ctx.input("collect"), obs_fn, picked, max_steps=cfg.max_episode_steps,
                              frame_skip=wm.spec.frame_skip, seed=cfg.seed)
        policy = load_policy(ctx.input("sft") / POLICY_FILE, ctx.device)
        policy.set_training_mode(False)
        t0 = time.perf_counter()
        try:
            with ctx.progress(len(specs), "wm_play: SFT policy plays in ManiSkill", unit="ep") as bar:
                play = play_episodes(policy, sim, specs, seeds, cfg.max_episode_steps, bar)
        finally:
            sim.close()
        t_play = time.perf_counter() - t0
        with checkpoints.save("play") as d:
            save_play(play, d)
            (d / "seconds.json").write_text(json.dumps(t_play))
    rows = [{"env_id": e.env_id, "seed": s, "policy_steps": int(p.length), "success": bool(p.done[-1] > 0)}
            for e, s, p in zip(picked, seeds, play)]
    (ctx.out / PLAY_JSON).write_text(json.dumps(rows, indent=1) + "\n")
    train = set(split["train"])
    train_eps = [e for e in load_episodes(ctx.input("collect"), ctx.input("tokenize"), frame_skip=wm.spec.frame_skip)
                 if e.episode_id in train]
    if ctx.device == "cpu":
        torch.set_num_threads(cfg.threads)  # training batches: the config's count, whatever the executor gave
    resume, save = training_checkpoint(checkpoints, "finetune")
    with ctx.progress(cfg.steps, "wm_play: world model on the play", unit="step") as bar:
        tuned, result = finetune_on_play(wm, wm_dir, train_eps, play, steps=cfg.steps, lr=cfg.lr, weight=cfg.weight,
                                         device=ctx.device, progress=bar, log=ctx.log, resume=resume, save=save,
                                         save_every=save_every(cfg.steps))
    save_world_model(tuned.net, ctx.out / CHECKPOINTS["action"],
                     {"decode_steps": tuned.decode_steps, "temperature": tuned.temperature})
    out = {"episodes": len(play), "successes": sum(r["success"] for r in rows),
           "policy_steps": sum(r["policy_steps"] for r in rows), "train_episodes": len(train_eps),
           "play_seconds": t_play, "finetune_seconds": result["seconds"],
           **{f"final_{k}": v for k, v in result["final"].items()}}
    ctx.log.info("wm_play: world model fine-tuned on the SFT policy's play: %s", out)
    return out


def action_world_model(wm_play_dir: str | Path, train_wm_dir: str | Path, device: str = "cpu"):
    """The action world model downstream stages use (``stages.train_wm.rollout.WorldModel``): train_wm's
    (its proprioception head, text embeddings, decoding settings) with the weights fine-tuned here when
    the wm_play artifact has them."""
    from stages.train_wm.rollout import CHECKPOINTS, load_net, load_world_model

    facts_path = Path(wm_play_dir) / WM_PLAY_JSON
    if not facts_path.is_file():
        raise FileNotFoundError(f"{facts_path} is missing: is {wm_play_dir} a committed wm_play artifact?")
    wm = load_world_model(train_wm_dir, kind="action", device=device)
    if json.loads(facts_path.read_text())["finetuned"]:
        tuned = load_net(Path(wm_play_dir) / CHECKPOINTS["action"], device)
        if tuned.spec != wm.spec:
            raise ValueError(f"the world model in {wm_play_dir} was not fine-tuned from the one in {train_wm_dir}: "
                             f"spec {tuned.spec} != {wm.spec}")
        wm.net.load_state_dict(tuned.state_dict())
    return wm


__all__ = ["Config", "run", "action_world_model", "WM_PLAY_JSON", "PLAY_JSON"]
