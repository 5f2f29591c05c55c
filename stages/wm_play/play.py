"""The SFT policy's play, recorded as world-model training episodes, and the fine-tune on it."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import torch

PLAY_SEED = 5_000_000  # play seeds: apart from training (< 1e6), evaluation and the precision check (3e6)


@torch.no_grad()
def play_episodes(policy, sim, specs: list, seeds: list[int], max_steps: int, progress=None) -> list:
    """One recorded episode per (spec, seed) as ``stages.train_wm.data.Episode`` at policy steps:
    tokens of the observed frames (T+1, N), executed actions (T, 7), success after each step (the
    first frame 0), proprioception (T+1, 10); kind ``play``."""
    from stages.sft.policy import act
    from stages.train_wm.data import Episode

    out = []
    for i, (spec, seed) in enumerate(zip(specs, seeds)):
        obs, _ = sim.reset(seed=seed, options={"spec": spec})
        frames, proprio, actions, done = [sim.tokens[0]], [obs["proprio"]], [], [0.0]  # tokens (h, w) of each frame
        for _ in range(max_steps):
            a = act(policy, {k: v[None] for k, v in obs.items()})[0]
            obs, _, term, trunc, info = sim.step(a)
            frames.append(sim.tokens[0]), proprio.append(obs["proprio"]), actions.append(a)
            done.append(float(info["success"]))
            if term or trunc:
                break
        tokens = torch.stack(frames).reshape(len(frames), -1).numpy()  # (T+1, N)
        out.append(Episode(f"play-{i}", sim.instruction, "ind", tokens.astype(np.int64),
                           np.stack(actions).astype(np.float32), np.asarray(done, np.float32),
                           np.stack(proprio).astype(np.float32), "play"))
        if progress is not None:
            progress.update(1)
    return out


def save_play(play: list, directory: Path) -> None:
    """The recorded play (``play_episodes``' output) as ``episodes.json`` + one ``.npz`` per episode."""
    meta = []
    for i, e in enumerate(play):
        np.savez(directory / f"{i:05d}.npz", tokens=e.tokens, actions=e.actions, done=e.done, proprio=e.proprio)
        meta.append({"episode_id": e.episode_id, "instruction": e.instruction, "split": e.split, "kind": e.kind})
    (directory / "episodes.json").write_text(json.dumps(meta, indent=1) + "\n")


def load_play(directory: Path) -> list:
    """The play ``save_play`` wrote, in order."""
    from stages.train_wm.data import Episode

    out = []
    for i, m in enumerate(json.loads((directory / "episodes.json").read_text())):
        with np.load(directory / f"{i:05d}.npz") as z:
            out.append(Episode(m["episode_id"], m["instruction"], m["split"], z["tokens"], z["actions"], z["done"],
                               z["proprio"], m["kind"]))
    return out


def finetune_on_play(wm, train_wm_dir, train_eps: list, play: list, *, steps: int, lr: float, weight: int,
                     device: str, progress=None, log=None, resume: dict | None = None, save=None, save_every: int = 0):
    """A copy of ``wm`` (``stages.train_wm.rollout.WorldModel``) trained ``steps`` more steps on
    ``train_eps`` + ``play`` x ``weight``, with train_wm's own losses and batch size (from its manifest).
    Returns (the copy in eval mode, the training result of ``train_world_model``). ``resume``, ``save``
    and ``save_every`` are ``train_world_model``'s: a fine-tune resumed from a saved state ends where
    the uninterrupted one does (tests/wm_play/test_play.py)."""
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
                               progress=progress, log=log, desc="play_wm", resume=resume, save=save,
                               save_every=save_every)
    tuned.net.eval()
    return tuned, result
