"""Filtered behaviour cloning in ManiSkill: the SFT policy plays, its successes join the demonstrations.

A probe for issue 13's target 1 (RL in ManiSkill above SFT in domain). PPO in ManiSkill at the
CPU budget (~20k policy steps, ~370 episodes) moves the arm by about one sampling std in a
direction no seed agrees on, and its training success stays flat (docs/RESULTS.md); the SFT policy,
though, is data-limited (half the demonstrations: 0.35 instead of 0.49 in domain, docs/sft.md), and
about 40% of the episodes PPO plays succeed. This probe spends the same simulator budget on that
instead: the SFT policy samples actions with its own noise (as PPO's first rollout does) on the IND
training environments, every episode the simulator calls a success becomes a demonstration (its
observations and executed actions, at policy steps), and the sft stage's recipe is rerun on the
demonstrations plus those episodes. With a 0/1 reward that is reward-weighted regression, i.e.
one round of policy improvement from the hand-written (success) reward; failed episodes are never
imitated. The rl stage runs the same method as ``rl.algorithm: filtered_bc`` (``stages.rl.filtered_bc``,
whose fit this probe calls); this probe keeps its variants (``--group``, ``--imitate mixed``,
``--init sft``, the recipe's own early stopping) and plays one simulator env with its own reset seeds.

    PYTHONPATH=. .venv/bin/python scripts/filtered_bc_probe.py <collect> <tokenize> <sft> --out DIR \
        [--steps 20096] [--seed 0] [--init scratch|sft] [--rounds 1]

Writes ``DIR/rollouts/round<k>/`` (one ``.npz`` per episode and ``episodes.jsonl``; a killed run
resumes there) and ``DIR/policy/``: an sft-shaped artifact (``sft_policy.pt``, ``policy.json``,
``text_embeddings.json``, ``split.json``, ``metrics.json``) that ``scripts/evaluate_sft.py
<collect> <tokenize> DIR/policy`` evaluates on the evaluate stage's states. With ``--rounds k`` the
budget is split into k rounds and each round's player is the previous round's policy (measured so far
only with k = 1: docs/RESULTS.md).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo root: runs without PYTHONPATH=.

ROLLOUT_SEED = 20_000_000  # reset seeds: apart from PPO training (< 1e6), evaluation and its acceptance test (1e6-2e7)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in ("collect", "tokenize", "sft"):
        ap.add_argument(name, type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=20_096, help="simulator policy steps in all (PPO's `rule` budget)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=1, help="rounds of play and fit, the budget split evenly")
    ap.add_argument("--init", choices=["scratch", "sft"], default="scratch",
                    help="scratch: the sft recipe from a fresh network; sft: continue from the SFT weights")
    ap.add_argument("--max-steps", type=int, default=75, help="policy steps per episode (the evaluation horizon)")
    ap.add_argument("--noise-scale", type=float, default=1.0, help="x the policy's own action std while playing")
    ap.add_argument("--group", type=int, default=1, help="episodes per initial state (the same reset seed): with "
                    "--imitate mixed only the successes of states that also failed are kept (a per-state baseline)")
    ap.add_argument("--imitate", choices=["all", "mixed"], default="all",
                    help="all: every successful episode; mixed: only those whose group also has a failure")
    ap.add_argument("--epochs", type=int, default=None, help="override the sft recipe's epochs (e.g. a short fine-tune)")
    ap.add_argument("--lr", type=float, default=None, help="override the sft recipe's peak learning rate")
    ap.add_argument("--keep", choices=["best", "last"], default=None, help="override the sft recipe's weights kept")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    for name in ("steps", "rounds", "group", "max_steps", "threads"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.noise_scale <= 0:
        ap.error(f"--noise-scale must be > 0, got {args.noise_scale}")

    import torch

    torch.set_num_threads(args.threads)
    player_dir = args.sft
    for k in range(args.rounds):
        rollouts = args.out / "rollouts" / f"round{k}"
        budget = args.steps // args.rounds
        play(args, player_dir, rollouts, budget, seed_offset=k)
        policy_dir = args.out / ("policy" if k == args.rounds - 1 else f"policy_round{k}")
        if not (policy_dir / "metrics.json").is_file():
            clone(args, [args.out / "rollouts" / f"round{j}" for j in range(k + 1)], policy_dir)
        player_dir = policy_dir


def play(args, player_dir: Path, out: Path, budget: int, seed_offset: int) -> None:
    """Episodes of ``player_dir``'s policy with sampled actions until ``budget`` policy steps (resumable)."""
    import torch

    from stages.common.environments import training_environments
    from stages.common.sim_env import sim_over
    from stages.goals.environments import list_environments
    from stages.sft import read_policy_json
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, act, load_policy
    from stages.tokenize.tokenizer import load_tokenizer

    out.mkdir(parents=True, exist_ok=True)
    log = out / "episodes.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.is_file() else []
    done_steps = sum(r["steps"] for r in rows)
    if done_steps >= budget:
        return
    info = read_policy_json(args.sft)
    split = json.loads((args.tokenize / "split.json").read_text())
    envs = training_environments(list_environments(args.collect), split["train"], list(info["tasks"]))
    obs_fn = ObservationFn.for_policy(load_tokenizer(args.tokenize, "cpu"),
                                      json.loads((args.sft / "text_embeddings.json").read_text()), info)
    sim, specs = sim_over(args.collect, obs_fn, envs, max_steps=args.max_steps, frame_skip=int(info["frame_skip"]),
                          seed=args.seed)
    policy = load_policy(player_dir / POLICY_FILE, "cpu")
    policy.set_training_mode(False)
    if args.noise_scale != 1.0:
        with torch.no_grad():
            policy.log_std.add_(float(np.log(args.noise_scale)))
    rng = np.random.default_rng([args.seed, seed_offset])
    picks = rng.integers(len(specs), size=budget)  # at most one episode per policy step
    t0, i = time.perf_counter(), len(rows)
    try:
        while done_steps < budget:
            g = i // args.group  # episodes of one group start from the same state
            spec, seed = specs[int(picks[g])], ROLLOUT_SEED + 100_000 * seed_offset + 1000 * args.seed + g
            obs, _ = sim.reset(seed=seed, options={"spec": spec})
            steps: list[tuple[dict, np.ndarray]] = []
            success = False
            for _ in range(args.max_steps):
                a = act(policy, {k: v[None] for k, v in obs.items()}, deterministic=False)[0]  # executed (7,)
                steps.append((obs, a))
                obs, _, term, trunc, sinfo = sim.step(a)
                if term or trunc:
                    success = bool(sinfo["success"])
                    break
            if success:
                np.savez_compressed(out / f"{i:05d}.npz", actions=np.stack([a for _, a in steps]),
                                    **{k: np.stack([o[k] for o, _ in steps]) for k in steps[0][0]})
            row = {"i": i, "group": g, "env": spec.key, "task": spec.task, "seed": seed, "steps": len(steps), "success": success}
            with log.open("a") as f:
                f.write(json.dumps(row) + "\n")
            rows.append(row)
            done_steps += len(steps)
            i += 1
            if i % 20 == 0:
                rate = sum(r["success"] for r in rows) / len(rows)
                print(f"[play {out.name}] {i} episodes, {done_steps}/{budget} steps, success {rate:.2f}, "
                      f"{time.perf_counter() - t0:.0f} s", flush=True)
    finally:
        sim.close()
    by_task: dict[str, list[bool]] = {}
    for r in rows:
        by_task.setdefault(r["task"], []).append(r["success"])
    print(f"[play {out.name}] done: {len(rows)} episodes, {done_steps} steps, successes "
          + ", ".join(f"{t} {sum(v)}/{len(v)}" for t, v in sorted(by_task.items())), flush=True)


def successes(dirs: list[Path], imitate: str = "all") -> tuple[dict[str, np.ndarray], np.ndarray, int]:
    """The recorded successful episodes' (observations, executed actions), concatenated: all of them, or
    (``mixed``) those whose group (initial state) also had a failure."""
    obs: dict[str, list] = {}
    acts, n = [], 0
    for d in dirs:
        rows = [json.loads(line) for line in (d / "episodes.jsonl").read_text().splitlines()]
        failed = {r.get("group", r["i"]) for r in rows if not r["success"]}
        keep = {r["i"] for r in rows if r["success"] and (imitate == "all" or r.get("group", r["i"]) in failed)}
        for f in sorted(d.glob("*.npz")):
            if int(f.stem) not in keep:
                continue
            with np.load(f) as z:
                for k in z.files:
                    if k != "actions":
                        obs.setdefault(k, []).append(z[k])
                acts.append(z["actions"])
            n += 1
    if not acts:
        raise ValueError(f"no successful episodes under {[str(d) for d in dirs]}")
    return {k: np.concatenate(v) for k, v in obs.items()}, np.concatenate(acts).astype(np.float32), n


def clone(args, rollout_dirs: list[Path], out: Path) -> None:
    """The sft stage's recipe on its own training demonstrations plus the successful rollouts
    (``stages.rl.filtered_bc.clone``, with this probe's overrides)."""
    from stages.collect.dataset import Dataset
    from stages.rl.filtered_bc import clone as fit, demonstration_pairs, joined, sft_recipe
    from stages.sft import read_policy_json
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, load_policy
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer

    recipe = sft_recipe(args.sft)
    overrides = {k: v for k, v in (("epochs", args.epochs), ("lr", args.lr), ("keep", args.keep)) if v is not None}
    recipe = recipe.model_copy(update=overrides)
    info = read_policy_json(args.sft)
    obs_fn = ObservationFn.for_policy(load_tokenizer(args.tokenize, "cpu"),
                                      json.loads((args.sft / "text_embeddings.json").read_text()), info)
    demos, val = demonstration_pairs(args.sft, info, Dataset(args.collect), TokenStore(args.tokenize), obs_fn)
    own_obs, own_act, n_own = successes(rollout_dirs, args.imitate)
    train = joined(demos, [(own_obs, own_act)])
    init = load_policy(args.sft / POLICY_FILE, "cpu") if args.init == "sft" else None
    print(f"[clone] {len(demos[1])} demonstration pairs + {n_own} own successes ({len(own_act)} pairs); "
          f"init {args.init}", flush=True)
    policy, new_info, facts = fit(recipe, info, obs_fn.space, train, val, epochs=recipe.epochs, device="cpu",
                                  keep=recipe.keep, init=init)
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    policy.save(str(tmp / POLICY_FILE))
    (tmp / "policy.json").write_text(json.dumps(new_info, indent=1) + "\n")
    for name in ("text_embeddings.json", "split.json"):
        shutil.copy(args.sft / name, tmp / name)
    metrics = {"own_successes": n_own, "own_pairs": int(len(own_act)), "demo_pairs": int(len(demos[1])),
               "epochs_run": facts["epochs"], "best_epoch": facts["best_epoch"], "loss/val_best": facts["loss_val_best"],
               "val/r2": facts["val_r2"], "fit_seconds": facts["fit_seconds"], "init": args.init,
               "imitate": args.imitate, "group": args.group, "overrides": overrides, "from_sft": str(args.sft)}
    (tmp / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    shutil.rmtree(out, ignore_errors=True)
    tmp.replace(out)
    print(f"[clone] {facts['epochs']} epochs (best {facts['best_epoch']}), held-out R^2 "
          f"{[round(v, 3) for v in facts['val_r2']]}, {facts['fit_seconds']:.0f} s -> {out}", flush=True)


if __name__ == "__main__":
    main()
