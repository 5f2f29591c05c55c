"""goals: one goal frame per environment (task x scene), for the dense reward.

Three goals per environment. ``generated`` (the paper, Eq. 6): the text WM rolls out from the
environment's initial frame, conditioned on its instruction, until its done head passes ``theta``,
sampling ``candidates`` futures and keeping the most confident. ``direct`` (the default): a jump
network predicts the goal in one step from the initial frame and the instruction (``direct.py``,
trained here on successful IND training episodes); at ``small`` its goals were 2.6x closer to the
real goal than the first frame out of domain, where the text WM's were farther (docs/rl.md).
``ground_truth``: the last frame of a successful demonstration (what the authors' code did with
``force_goal``). All three are always computed where
possible, so the artifact reports how far each is from the real goal (LPIPS), next to the initial
frame's distance.

Inputs:
    collect -- episodes (environments, instructions, successful demos)
    tokenize -- token store (initial and last frames as tokens) and the tokenizer (decoding)
    train_wm -- the text world model (``text_wm.pt``)

Outputs:
    goals.npz     env_ids (E,), tokens (E, h, w) uint16 = THE goal per ``goal_mode``,
                  generated_tokens / done_prob / steps / reached (E,) of the imagined goals,
                  direct_tokens (E, h, w) of the direct predictor,
                  ground_truth_tokens (E, h, w) and has_ground_truth (E,)
    goals.json    per environment: task, scene, split, instruction, chosen goal, done prob, steps
    goals.png     initial frame | imagined goal | direct goal | ground-truth goal (third view)
    goal_predictor.pt  the direct predictor (``stages.train_wm.rollout.load_net``)
    metrics.json  fraction of environments whose imagined goal passed theta, mean steps, mean done
                  prob, per split: LPIPS(imagined, ground truth) next to LPIPS(first frame, ground
                  truth) (a goal that copies the start scores the latter), and the fraction of
                  environments whose imagined goal is the closer one

Key includes:
    this config (goal_mode, theta, max_steps, candidates, temperature, seed) and the keys of
    collect, tokenize and train_wm.

Toy profile:
    2 candidates, at most 8 imagined steps; every environment of the toy collection.
"""
from __future__ import annotations

import json
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from stages.goals.environments import list_environments
from stages.goals.figure import goal_grid, to_uint8
from stages.goals.imagine import imagine_goals

GOALS = "goals.npz"


class Config(BaseModel):
    """goals stage configuration (defaults sized for the ``small`` profile)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, description="seed of the candidate sampling")
    goal_mode: Literal["generated", "direct", "ground_truth"] = Field(
        "direct", description="direct: one-step goal predictor (stages.goals.direct; the default, measured "
        "closer to the real goal); generated: imagined by the text WM (the paper); ground_truth: last frame of a "
        "successful demo")
    theta: float = Field(0.5, gt=0, lt=1, description="done-head threshold that ends an imagined rollout")
    max_steps: int = Field(60, ge=1, description="cap on imagined world-model steps per candidate (x frame_skip control steps)")
    candidates: int = Field(4, ge=1, description="imagined rollouts per environment; the most confident is kept")
    temperature: float = Field(1.0, ge=0, description="token sampling temperature of the candidates (0 = greedy)")
    batch_size: int = Field(64, ge=1, description="imagined rollouts stepped together")
    direct_dim: int = Field(128, ge=8, description="width of the direct goal predictor")
    direct_depth: int = Field(3, ge=1, description="blocks of the direct goal predictor")
    direct_steps: int = Field(1500, ge=1, description="optimisation steps of the direct goal predictor")
    direct_batch_size: int = Field(16, ge=1, description="(frame, last frame) pairs per step")
    direct_decode_steps: int = Field(8, ge=1, description="MaskGIT passes decoding a direct goal (most tokens change)")


def run(ctx) -> None:
    from stages.common.image_metrics import lpips as lpips_distance
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.rollout import load_world_model

    cfg: Config = ctx.config
    if ctx.device == "cpu":
        torch.set_num_threads(1)
    store = TokenStore(ctx.input("tokenize"))
    tok = load_tokenizer(ctx.input("tokenize"), ctx.device)
    envs = list_environments(ctx.input("collect"))
    if not envs:
        raise ValueError(f"no environments in {ctx.input('collect')}")
    # the start and the real goal come from the same successful demonstration (same initial state),
    # so LPIPS(first frame, real goal) and LPIPS(imagined goal, real goal) compare like with like
    first_ep = [e.successful[0] if e.successful else e.episodes[0] for e in envs]
    start = np.stack([np.asarray(store.episode(i)[0], dtype=np.int64) for i in first_ep])  # (E, h, w)
    has_gt = np.array([bool(e.successful) for e in envs])
    gt = np.stack([np.asarray(store.episode(e.successful[0])[-1], dtype=np.int64) if e.successful else start[i]
                   for i, e in enumerate(envs)])  # (E, h, w)

    direct = _direct_goals(ctx, cfg, store, envs, start)
    wm = load_world_model(ctx.input("train_wm"), kind="text", device=ctx.device, temperature=cfg.temperature)
    per_batch = max(1, cfg.batch_size // cfg.candidates)
    parts = []
    with ctx.progress(cfg.max_steps * ((len(envs) + per_batch - 1) // per_batch), "imagine goals", unit="step") as bar:
        for i in range(0, len(envs), per_batch):
            sl = slice(i, i + per_batch)
            parts.append(imagine_goals(wm, torch.from_numpy(start[sl]).to(ctx.device), [e.instruction for e in envs[sl]],
                                       theta=cfg.theta, max_steps=cfg.max_steps, candidates=cfg.candidates,
                                       seed=cfg.seed + i, progress=bar))
    gen = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("tokens", "done_prob", "steps", "reached")}
    if cfg.goal_mode == "generated":
        chosen = gen["tokens"]
    elif cfg.goal_mode == "direct":
        chosen = direct
    else:
        missing = [e.env_id for e, ok in zip(envs, has_gt) if not ok]
        if missing:
            ctx.log.warning("goals: %d environments have no successful demo; their ground-truth goal is the "
                            "initial frame: %s", len(missing), missing[:5])
        chosen = gt
    np.savez(ctx.out / GOALS, env_ids=np.array([e.env_id for e in envs]), tokens=chosen.astype(np.uint16),
             generated_tokens=gen["tokens"].astype(np.uint16), direct_tokens=direct.astype(np.uint16),
             done_prob=gen["done_prob"], steps=gen["steps"],
             reached=gen["reached"], ground_truth_tokens=gt.astype(np.uint16), has_ground_truth=has_gt,
             goal_mode=np.array(cfg.goal_mode))

    def decoded(tokens: np.ndarray) -> list[torch.Tensor]:  # (E, h, w) -> [third, wrist] (E, 3, S, S) on the CPU
        return [v.cpu() for v in tok.decode(torch.from_numpy(tokens))]

    third_gen, wrist_gen = decoded(gen["tokens"])
    third_gt, wrist_gt = decoded(gt)
    third_start, wrist_start = decoded(start)

    def to_real_goal(third: torch.Tensor, wrist: torch.Tensor) -> np.ndarray:  # (E,) LPIPS, both views averaged
        d = lpips_distance(third, third_gt, device=ctx.device) + lpips_distance(wrist, wrist_gt, device=ctx.device)
        return (0.5 * d).cpu().numpy()

    third_dir, wrist_dir = decoded(direct)
    dist, dist_first = to_real_goal(third_gen, wrist_gen), to_real_goal(third_start, wrist_start)
    dist_direct = to_real_goal(third_dir, wrist_dir)
    meta = []
    for i, e in enumerate(envs):
        meta.append({"env_id": e.env_id, "task": e.task, "scene_id": e.scene_id, "split": e.split,
                     "instruction": e.instruction, "goal_mode": cfg.goal_mode,
                     "imagined": {"done_prob": float(gen["done_prob"][i]), "steps": int(gen["steps"][i]),
                                  "reached": bool(gen["reached"][i])},
                     "ground_truth_episode": e.successful[0] if e.successful else None,
                     "lpips_imagined_vs_ground_truth": float(dist[i]) if has_gt[i] else None,
                     "lpips_first_vs_ground_truth": float(dist_first[i]) if has_gt[i] else None,
                     "lpips_direct_vs_ground_truth": float(dist_direct[i]) if has_gt[i] else None})
    (ctx.out / "goals.json").write_text(json.dumps(meta, indent=1) + "\n")
    goal_grid([(e.env_id, [to_uint8(third_start[i]), to_uint8(third_gen[i]), to_uint8(third_dir[i]),
                           to_uint8(third_gt[i]) if has_gt[i] else None]) for i, e in enumerate(envs)],
              ["initial", "imagined goal", "direct goal", "ground-truth goal"], ctx.out / "goals.png")

    metrics: dict = {"environments": len(envs), "goal_mode": cfg.goal_mode}
    for split in ("ind", "ood"):
        idx = np.array([i for i, e in enumerate(envs) if e.split == split], dtype=int)
        if len(idx) == 0:
            continue
        metrics[f"{split}/environments"] = int(len(idx))
        metrics[f"{split}/imagined_reached_theta"] = float(gen["reached"][idx].mean())
        metrics[f"{split}/imagined_steps_mean"] = float(gen["steps"][idx].mean())
        metrics[f"{split}/imagined_done_prob_mean"] = float(gen["done_prob"][idx].mean())
        with_gt = idx[has_gt[idx]]
        if len(with_gt):
            metrics[f"{split}/lpips_imagined_vs_ground_truth"] = float(dist[with_gt].mean())
            metrics[f"{split}/lpips_first_vs_ground_truth"] = float(dist_first[with_gt].mean())
            metrics[f"{split}/imagined_closer_than_first"] = float((dist[with_gt] < dist_first[with_gt]).mean())
            metrics[f"{split}/lpips_direct_vs_ground_truth"] = float(dist_direct[with_gt].mean())
            metrics[f"{split}/direct_closer_than_first"] = float((dist_direct[with_gt] < dist_first[with_gt]).mean())
    ctx.log.info("goals: %s", metrics)
    ctx.write_metrics(metrics)


def _direct_goals(ctx, cfg: Config, store, envs: list, start: np.ndarray) -> np.ndarray:
    """Train the direct goal predictor on successful IND training episodes; its goals (E, h, w)."""
    from stages.collect.dataset import Dataset
    from stages.goals.direct import jump_clips, predict_goals, train_goal_predictor
    from stages.train_wm.rollout import TEXT_EMBEDDINGS, save_world_model

    wm_dir = ctx.input("train_wm")
    train_ids = set(json.loads((wm_dir / "split.json").read_text())["train"])
    text_emb = {k: np.asarray(v, np.float32) for k, v in json.loads((wm_dir / TEXT_EMBEDDINGS).read_text()).items()}
    demos = [m for m in Dataset(ctx.input("collect")).episodes if m.episode_id in train_ids and m.success]
    if not demos:
        raise ValueError("no successful IND training episodes to fit the direct goal predictor on")
    with ctx.progress(cfg.direct_steps, "goals: direct goal predictor", unit="step") as bar:
        net, result = train_goal_predictor(jump_clips(store, demos), text_emb, vocab=2**store.bits, grid=tuple(store.grid),
                                           dim=cfg.direct_dim, depth=cfg.direct_depth, steps=cfg.direct_steps,
                                           batch_size=cfg.direct_batch_size, lr=1e-3, seed=cfg.seed,
                                           device=ctx.device, progress=bar)
    save_world_model(net, ctx.out / "goal_predictor.pt", {"decode_steps": cfg.direct_decode_steps})
    ctx.log.info("goals: direct predictor on %d demos, final ce %.3f acc %.3f, %.0f s", len(demos),
                 result["final"]["ce"], result["final"]["acc"], result["seconds"])
    return predict_goals(net, torch.from_numpy(start).to(ctx.device), [e.instruction for e in envs], text_emb,
                         cfg.direct_decode_steps)


def load_goals(goals_dir) -> dict:
    """The goals artifact as numpy arrays (see Outputs); ``env_ids`` as a list of str."""
    from pathlib import Path

    with np.load(Path(goals_dir) / GOALS) as z:
        out = {k: z[k] for k in z.files}
    out["env_ids"] = [str(s) for s in out["env_ids"]]
    out["goal_mode"] = str(out["goal_mode"])
    return out
