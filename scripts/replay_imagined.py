"""Does a policy exploit the world model? The rl stage's imagined-success check, for any policy.

The rl stage measures this for its final policy (``imagined/<split>/precision`` in its
metrics.json, rows in imagined.json); this script runs the same code (``stages.rl.imagined``) on
the SFT policy or a PPO snapshot, with other environment counts or thresholds:

    PYTHONPATH=. .venv/bin/python scripts/replay_imagined.py <collect> <tokenize> <train_wm> <sft> <rl> \\
        [--policy ppo|sft|snapshots/step_N.zip] [--envs 24] [--steps 75] [--split ind]

Prints imagined done (done head >= theta at any step), simulator success of the replayed actions,
precision with its Wilson 95% interval, and one line per environment.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in ("collect", "tokenize", "train_wm", "sft", "rl"):
        ap.add_argument(name, type=Path)
    ap.add_argument("--policy", default="ppo", help="ppo (rl's policy.zip), sft, or a path inside the rl artifact")
    ap.add_argument("--envs", type=int, default=24, help="environments of the split (spread over the tasks)")
    ap.add_argument("--split", choices=["ind", "ood"], default="ind")
    ap.add_argument("--steps", type=int, default=75, help="policy steps (rl.max_episode_steps)")
    ap.add_argument("--theta", type=float, default=0.5, help="done-head threshold (rl.theta_done)")
    ap.add_argument("--seed", type=int, default=2_000_000)
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.collect.catalog import read_scenes_json
    from stages.collect.dataset import read_sim_facts
    from stages.goals.environments import list_environments
    from stages.rl.imagined import imagine_and_replay, pick_environments, precision_metrics
    from stages.rl.sim_env import SimSpec, SimTaskEnv
    from stages.sft import TEXT_EMBEDDINGS, read_policy_json
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, load_policy
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.rollout import load_world_model

    tok = load_tokenizer(args.tokenize, "cpu")
    obs_fn = ObservationFn(tok, json.loads((args.sft / TEXT_EMBEDDINGS).read_text()))
    wm = load_world_model(args.train_wm, "action", "cpu")
    path = {"ppo": args.rl / "policy.zip", "sft": args.sft / POLICY_FILE}.get(args.policy, args.rl / args.policy)
    policy = load_policy(path, "cpu")
    tasks = read_policy_json(args.sft)["tasks"]
    scenes, facts = read_scenes_json(args.collect / "scenes.json"), read_sim_facts(args.collect)
    picked = pick_environments([e for e in list_environments(args.collect) if e.split == args.split and e.task in tasks],
                               args.envs)
    specs = [SimSpec(e.task, scenes[e.scene_id].to_dict(), e.instruction) for e in picked]
    sim = SimTaskEnv(specs, obs_fn, max_steps=args.steps, action_repeat=int(wm.spec.frame_skip),
                     image_size=facts.image_size, robot_mesh=facts.robot_mesh)
    try:
        rows = imagine_and_replay(policy, wm, tok, obs_fn, sim, specs, [args.seed + i for i in range(len(specs))],
                                  args.steps, args.theta)
    finally:
        sim.close()
    m = precision_metrics(rows)
    print(f"policy {args.policy}: {m['environments']} {args.split.upper()} environments, horizon {args.steps} policy steps")
    print(f"  imagined done {m['imagined_done']}, replayed success {m['replayed_success']}, both {m['imagined_and_replayed']}")
    if m["precision"] is not None:
        print(f"  precision {m['precision']:.2f} [{m['precision_lo']:.2f}, {m['precision_hi']:.2f}]")
    for r in rows:
        print(f"    {r.env_id:55s} done_at {r.done_at:3d}  replay success {r.success}")


if __name__ == "__main__":
    main()
