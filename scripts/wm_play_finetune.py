"""Does the world model stop imagining false successes once it has seen the policy fail?

Every collected episode is planned, so the action world model has never watched what happens when a
learned policy's gripper misses: inside it, the SFT policy's imagined successes are mostly not real
(docs/RESULTS.md, "Where the imagination goes wrong"). This script lets the SFT policy play
``--episodes`` episodes in ManiSkill (IND training environments, seeds apart from every check's),
records them at the world model's step (tokens of the observed frame, proprioception, the executed
action, the success flag: failures included), and fine-tunes the action world model for
``--steps`` steps on its training episodes plus these (the play episodes listed ``--play-weight``
times). It writes a copy of the train_wm artifact directory with the new ``action_wm.pt``, so
``scripts/replay_imagined.py`` takes it as it is (run it on seeds the play never used: its default).

    PYTHONPATH=. .venv/bin/python scripts/wm_play_finetune.py <collect> <tokenize> <train_wm> <sft> --out DIR \\
        [--episodes 96] [--max-steps 50] [--steps 1000] [--lr 3e-4] [--play-weight 2] [--policy FILE]

``--policy <rl>/policy.zip`` lets a PPO policy play instead of the SFT policy; with ``--wm-play <wm_play>``
(the world model that policy trained in) this is a second round of play: the world model sees where
the policy trained in it goes wrong.

``--episodes 0`` is the control: the same fine-tune on the training episodes alone (no play), which
separates what the play data do from what the extra training steps do. The ``wm_play`` stage does the
same inside the pipeline (stages/wm_play), and the rl stage trains PPO in the result.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch


def main() -> None:
    from policy_check import add_artifact_args, load_check

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_artifact_args(ap)
    ap.add_argument("--out", type=Path, required=True, help="directory: a copy of the train_wm artifact with the new model")
    ap.add_argument("--episodes", type=int, default=96)
    ap.add_argument("--max-steps", type=int, default=50)
    ap.add_argument("--steps", type=int, default=1000, help="fine-tuning steps of the action world model")
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--play-weight", type=int, default=2, help="how many times the play episodes are listed")
    ap.add_argument("--seed", type=int, default=5_000_000, help="first play seed (the checks use 2_000_000+)")
    ap.add_argument("--policy", type=Path, default=None,
                    help="the policy that plays: a policy file (an rl artifact's policy.zip, say); default the SFT policy")
    ap.add_argument("--threads", type=int, default=2, help="torch threads of the fine-tune")
    args = ap.parse_args()

    from stages.wm_play.play import finetune_on_play, play_episodes
    from stages.sft.policy import POLICY_FILE
    from stages.train_wm.data import load_episodes
    from stages.train_wm.rollout import CHECKPOINTS, save_world_model

    torch.set_num_threads(1)
    if args.episodes < 0:
        raise ValueError(f"--episodes must be >= 0, got {args.episodes}")
    c = load_check(args.collect, args.tokenize, args.train_wm, args.sft, args.policy or args.sft / POLICY_FILE, split="ind",
                   envs=max(args.episodes, 1), steps=args.max_steps, wm_play=args.wm_play)
    t0 = time.perf_counter()
    try:
        eps = play_episodes(c.policy, c.sim, c.specs[:args.episodes], [args.seed + i for i in range(args.episodes)],
                            args.max_steps)
    finally:
        c.sim.close()
    wins = sum(e.done[-1] > 0 for e in eps)
    print(f"play: {len(eps)} episodes ({wins} successes, {sum(e.length for e in eps)} steps) in {time.perf_counter() - t0:.0f} s")

    split = set(json.loads((args.train_wm / "split.json").read_text())["train"])
    train = [e for e in load_episodes(args.collect, args.tokenize, frame_skip=int(c.wm.spec.frame_skip))
             if e.episode_id in split]
    torch.set_num_threads(args.threads)
    wm, result = finetune_on_play(c.wm, args.train_wm, train, eps, steps=args.steps, lr=args.lr,
                                  weight=args.play_weight, device="cpu")
    net = wm.net
    print(f"fine-tuned {args.steps} steps in {result['seconds']:.0f} s: ce {result['final']['ce']:.3f}, "
          f"acc {result['final']['acc']:.3f}, done {result['final']['done']:.4f}")
    args.out.mkdir(parents=True, exist_ok=True)
    for f in args.train_wm.iterdir():
        if f.name != CHECKPOINTS["action"] and f.is_file() and not (args.out / f.name).exists():
            (args.out / f.name).symlink_to(f.resolve())
    save_world_model(net, args.out / CHECKPOINTS["action"],
                     {"decode_steps": c.wm.decode_steps, "temperature": c.wm.temperature})
    print(f"world model: {args.out / CHECKPOINTS['action']}")


if __name__ == "__main__":
    main()
