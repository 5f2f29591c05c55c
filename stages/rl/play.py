"""The action world model fine-tuned on the SFT policy's own play (``rl.wm_play_episodes``).

Every collected episode is planner-made (optimal, perturbed, near-miss), so the world model has never
watched a learned policy act: under the policy's actions it imagines demonstration-like progress that
does not happen, and most imagined successes are not real (docs/RESULTS.md). With ``wm_play_episodes``
> 0 the SFT policy first plays that many episodes in ManiSkill on the IND training environments,
recorded at the world model's step with their failures; a copy of the action world model is then
fine-tuned on its own training episodes plus the play (listed ``wm_play_weight`` times), and
everything after it in the stage (reward heads, diagnostics, PPO, the precision check) uses the copy.
Like the guard's replays this spends simulator steps before PPO, on training environments only: a
departure from the paper's simulator-free training, off by default.
"""
from __future__ import annotations

import copy
import json
import time

import numpy as np
import torch

PLAY_SEED = 5_000_000  # play seeds: apart from training (< 1e6), evaluation and the precision check (3e6)
PLAY_WM = "play_action_wm.pt"  # the fine-tuned action world model, in the rl artifact


@torch.no_grad()
def play_episodes(policy, sim, specs: list, seeds: list[int], max_steps: int, progress=None) -> list:
    """One recorded episode per (spec, seed) as ``stages.train_wm.data.Episode`` at policy steps:
    tokens of the observed frames (T+1, N), executed actions (T, 7), success after each step (the
    first frame 0), proprioception (T+1, 10); kind ``play``."""
    from stages.sft.policy import act
    from stages.tokenize.lfq import codes_to_tokens
    from stages.train_wm.data import Episode

    out = []
    for i, (spec, seed) in enumerate(zip(specs, seeds)):
        obs, _ = sim.reset(seed=seed, options={"spec": spec})
        codes, proprio, actions, done = [obs["codes"]], [obs["proprio"]], [], [0.0]
        for _ in range(max_steps):
            a = act(policy, {k: v[None] for k, v in obs.items()})[0]
            obs, _, term, trunc, info = sim.step(a)
            codes.append(obs["codes"]), proprio.append(obs["proprio"]), actions.append(a)
            done.append(float(info["success"]))
            if term or trunc:
                break
        tokens = codes_to_tokens(torch.as_tensor(np.stack(codes))).reshape(len(codes), -1).numpy()  # (T+1, N)
        out.append(Episode(f"play-{i}", sim.instruction, "ind", tokens.astype(np.int64),
                           np.stack(actions).astype(np.float32), np.asarray(done, np.float32),
                           np.stack(proprio).astype(np.float32), "play"))
        if progress is not None:
            progress.update(1)
    return out


def finetune_on_play(wm, train_wm_dir, train_eps: list, play: list, *, steps: int, lr: float, weight: int,
                     device: str, progress=None, log=None):
    """A copy of ``wm`` (``stages.train_wm.rollout.WorldModel``) trained ``steps`` more steps on
    ``train_eps`` + ``play`` x ``weight``, with train_wm's own losses and batch size (from its manifest).
    Returns (the copy in eval mode, the training result of ``train_world_model``)."""
    from stages.train_wm.data import ClipSampler
    from stages.train_wm.rollout import TEXT_EMBEDDINGS
    from stages.train_wm.train import train_world_model

    cfg = json.loads((train_wm_dir / "manifest.json").read_text())["key_inputs"]["config"]
    text = {k: np.asarray(v, np.float32) for k, v in json.loads((train_wm_dir / TEXT_EMBEDDINGS).read_text()).items()}
    missing = sorted({e.instruction for e in play} - set(text))
    if missing:
        raise ValueError(f"play instructions without a text embedding in {train_wm_dir}: {missing[:3]}")
    tuned = copy.deepcopy(wm)
    sampler = ClipSampler(train_eps + play * weight, cfg["window"], text, cfg["seed"] + 99)
    result = train_world_model(tuned.net, sampler, steps=steps, batch_size=cfg["batch_size"], lr=lr,
                               weight_decay=cfg["weight_decay"], done_weight=cfg["done_weight"],
                               done_kind=cfg["done_loss"], seed=cfg["seed"] + 7, device=device,
                               changed_weight=cfg["changed_weight"], done_balance=cfg["done_balance"],
                               context_noise=cfg.get("context_noise", 0.0), self_context=cfg.get("self_context", 0.0),
                               progress=progress, log=log, desc="play_wm")
    tuned.net.eval()
    return tuned, result


def play_and_finetune(ctx, cfg, inp, envs: list) -> dict:
    """Let the SFT policy play ``cfg.wm_play_episodes`` training environments, fine-tune the world
    model on it, put the copy in ``inp.wm`` and save it; returns the ``wm_play/...`` metrics."""
    from stages.rl.imagined import pick_environments
    from stages.rl.train import replay_sim
    from stages.train_wm.data import load_episodes
    from stages.train_wm.rollout import save_world_model

    picked = pick_environments(envs, cfg.wm_play_episodes)
    sim, specs = replay_sim(ctx, cfg, inp, picked)
    seeds = [PLAY_SEED + 1000 * cfg.seed + i for i in range(len(specs))]
    t0 = time.perf_counter()
    inp.sft_policy.set_training_mode(False)
    try:
        with ctx.progress(len(specs), "rl: SFT policy plays in ManiSkill", unit="ep") as bar:
            play = play_episodes(inp.sft_policy, sim, specs, seeds, cfg.max_episode_steps, bar)
    finally:
        sim.close()
    t_play = time.perf_counter() - t0
    train = set(inp.split["train"])
    train_eps = [e for e in load_episodes(ctx.input("collect"), ctx.input("tokenize"), frame_skip=inp.frame_skip)
                 if e.episode_id in train]
    with ctx.progress(cfg.wm_play_steps, "rl: world model on the play", unit="step") as bar:
        inp.wm, result = finetune_on_play(inp.wm, ctx.input("train_wm"), train_eps, play, steps=cfg.wm_play_steps,
                                          lr=cfg.wm_play_lr, weight=cfg.wm_play_weight, device=inp.device,
                                          progress=bar, log=ctx.log)
    save_world_model(inp.wm.net, ctx.out / PLAY_WM,
                     {"decode_steps": inp.wm.decode_steps, "temperature": inp.wm.temperature})
    out = {"wm_play/episodes": len(play), "wm_play/successes": int(sum(e.done[-1] > 0 for e in play)),
           "wm_play/policy_steps": int(sum(e.length for e in play)), "wm_play/train_episodes": len(train_eps),
           "wm_play/play_seconds": t_play, "wm_play/finetune_seconds": result["seconds"],
           **{f"wm_play/final_{k}": v for k, v in result["final"].items()}}
    ctx.log.info("rl: world model fine-tuned on the SFT policy's play: %s", out)
    return out
