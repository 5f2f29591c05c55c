"""Does a policy fine-tuned on the world model's own frames act in imagination as it acts in reality?

Inside the action world model the SFT policy reads its next action off imagined frames, and the
action sequences it produces there succeed in ManiSkill far less often than the ones it produces on
real frames (docs/RESULTS.md, "Where the imagination goes wrong"). This script builds, along the SFT
artifact's demonstrations, the observations the policy would see inside the world model: from every
``--every``-th step of a demonstration, the world model rolls ``--horizon`` steps open loop under the
demonstration's own actions (frames and proprioception head, as in the rl stage), and each imagined
frame is paired with the demonstration's next action. The SFT policy is then fine-tuned by behaviour
cloning on the real pairs plus these imagined ones, and written as a copy of the SFT artifact
directory with the new ``sft_policy.pt`` (so ``scripts/replay_imagined.py ... --policy sft`` and
``scripts/evaluate_sft.py`` take it as they are).

    PYTHONPATH=. .venv/bin/python scripts/wm_obs_finetune.py <collect> <tokenize> <train_wm> <sft> --out DIR \\
        [--horizon 12] [--every 3] [--epochs 10] [--lr 1e-4]

Prints the held-out loss on real and on imagined pairs before and after.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


@torch.no_grad()
def imagined_pairs(wm, obs_fn, demos: list, horizon: int, every: int, batch: int = 64):
    """Observations inside the world model along ``demos`` and the demonstrations' actions there.

    Returns (obs dict over M pairs, actions (M, 7)): for each start s (every ``every`` steps, with at
    least 2 steps left) the imagined frame and proprioception after k = 1 .. horizon-1 open-loop
    steps under the recorded actions, paired with the recorded action at s + k.
    """
    starts = [(d, s) for d in demos for s in range(0, len(d.actions) - 1, every)]
    tokens, proprio, instr, acts, first = [], [], [], [], []
    for i in range(0, len(starts), batch):
        chunk = starts[i: i + batch]
        n = len(chunk)
        roll = wm.rollout(n)
        roll.reset(torch.as_tensor(np.stack([d.tokens[s] for d, s in chunk])))
        p = torch.as_tensor(np.stack([d.proprio[s] for d, s in chunk]))  # (n, 10)
        for k in range(horizon - 1):
            live = [j for j, (d, s) in enumerate(chunk) if s + k + 1 < len(d.actions)]  # a next action exists
            if not live:
                break
            a = torch.as_tensor(np.stack([d.actions[min(s + k, len(d.actions) - 1)] for d, s in chunk]))  # (n, 7)
            out = roll.step(a)
            p = wm.next_proprio(p, a, out.tokens)
            for j in live:
                d, s = chunk[j]
                tokens.append(out.tokens[j].numpy()), proprio.append(p[j].numpy()), instr.append(d.instruction)
                first.append(d.tokens[0])
                acts.append(d.actions[s + k + 1])
    obs = obs_fn.from_tokens(np.stack(tokens), np.stack(proprio).astype(np.float32), instr, first=np.stack(first))
    return obs, np.stack(acts).astype(np.float32)


def _concat(a: tuple[dict, np.ndarray], b: tuple[dict, np.ndarray]) -> tuple[dict, np.ndarray]:
    return {k: np.concatenate([a[0][k], b[0][k]]) for k in a[0]}, np.concatenate([a[1], b[1]])


def main() -> None:
    from policy_check import add_artifact_args

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_artifact_args(ap)
    ap.add_argument("--out", type=Path, required=True, help="directory: a copy of the sft artifact with the new policy")
    ap.add_argument("--horizon", type=int, default=12, help="open-loop world-model steps from each start")
    ap.add_argument("--every", type=int, default=3, help="a start every this many demonstration steps")
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(2)

    from stages.collect.dataset import Dataset
    from stages.sft import TEXT_EMBEDDINGS
    from stages.sft.data import load_demo, pairs
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import POLICY_FILE, TaskPolicy, behaviour_clone, dim_weights, evaluate_pairs
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.rollout import load_world_model

    cfg = json.loads((args.sft / "manifest.json").read_text())["key_inputs"]["config"]
    split = json.loads((args.sft / "split.json").read_text())
    ds, store = Dataset(args.collect), TokenStore(args.tokenize)
    obs_fn = ObservationFn.for_policy(load_tokenizer(args.tokenize, "cpu"), json.loads((args.sft / TEXT_EMBEDDINGS).read_text()),
                                      json.loads((args.sft / "policy.json").read_text()))
    wm = load_world_model(args.train_wm, "action", "cpu")
    if args.wm_play is not None:
        from stages.wm_play import action_world_model

        wm = action_world_model(args.wm_play, args.train_wm)
    if int(wm.spec.frame_skip) != int(cfg["frame_skip"]):
        raise ValueError(f"world model frame_skip {wm.spec.frame_skip} != SFT frame_skip {cfg['frame_skip']}")
    load = lambda ids: [load_demo(ds, store, i, cfg["frame_skip"], cfg["retime_min_move"],  # noqa: E731
                                  max(cfg["retime_max_gap"], cfg["frame_skip"])) for i in ids]
    train_demos, val_demos = load(split["train"]), load(split["val"])
    real_train, real_val = pairs(train_demos, obs_fn), pairs(val_demos, obs_fn)
    im_train = imagined_pairs(wm, obs_fn, train_demos, args.horizon, args.every)
    im_val = imagined_pairs(wm, obs_fn, val_demos, args.horizon, args.every)
    print(f"pairs: real {len(real_train[1])} train / {len(real_val[1])} held out; imagined {len(im_train[1])} / {len(im_val[1])}")

    policy = TaskPolicy.load(str(args.sft / POLICY_FILE), device="cpu")
    weights = dim_weights(cfg["gripper_weight"], cfg["rotation_weight"])
    before = {n: evaluate_pairs(policy, p, weights)["loss"] for n, p in (("real", real_val), ("imagined", im_val))}
    hist = behaviour_clone(policy, _concat(real_train, im_train), _concat(real_val, im_val), epochs=args.epochs,
                           lr=args.lr, weight_decay=cfg["weight_decay"], batch_size=cfg["batch_size"],
                           patience=args.epochs, weights=weights, seed=args.seed, keep="best")
    after = {n: evaluate_pairs(policy, p, weights)["loss"] for n, p in (("real", real_val), ("imagined", im_val))}
    print(f"held-out loss before: real {before['real']:.3f}, imagined {before['imagined']:.3f}; after "
          f"(best of {hist['epochs_run']} epochs, epoch {hist['best_epoch']}): real {after['real']:.3f}, "
          f"imagined {after['imagined']:.3f}")
    args.out.mkdir(parents=True, exist_ok=True)
    for f in args.sft.iterdir():  # the SFT artifact's other files, as they are
        if f.name != POLICY_FILE and f.is_file() and not (args.out / f.name).exists():
            (args.out / f.name).symlink_to(f.resolve())
    policy.save(str(args.out / POLICY_FILE))
    print(f"policy: {args.out / POLICY_FILE}")


if __name__ == "__main__":
    main()
