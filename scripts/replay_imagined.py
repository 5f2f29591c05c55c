"""Does a policy exploit the world model? The rl stage's imagined-success check, for any policy.

The rl stage measures this for its final policy (``imagined/<split>/precision`` in its
metrics.json, rows in imagined.json); this script runs the same code (``stages.rl.imagined``) on
the SFT policy or a PPO snapshot, with other environment counts or thresholds:

    PYTHONPATH=. .venv/bin/python scripts/replay_imagined.py <collect> <tokenize> <train_wm> <sft> <rl> \\
        [--policy ppo|sft|snapshots/step_N.zip] [--envs 24] [--steps 75] [--split ind] [--thetas 0.7 0.9]

Prints imagined done (done head >= theta at any step), simulator success of the replayed actions,
precision with its Wilson 95% interval, the same at each stricter threshold of ``--thetas`` (from the
same rollouts), the largest imagined-vs-replayed TCP gap up to each imagined success (confirmed by
the replay or not), and one line per environment.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch


def main() -> None:
    from policy_check import add_artifact_args, add_decoding_options, add_wm_net_option, load_check

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_artifact_args(ap, ("collect", "tokenize", "train_wm", "sft", "rl"))
    ap.add_argument("--policy", default="ppo", help="ppo (rl's policy.zip), sft, or a path inside the rl artifact")
    ap.add_argument("--envs", type=int, default=24, help="environments of the split (spread over the tasks)")
    ap.add_argument("--split", choices=["ind", "ood"], default="ind")
    ap.add_argument("--steps", type=int, default=75, help="policy steps (rl.max_episode_steps)")
    ap.add_argument("--theta", type=float, default=0.5, help="done-head threshold (rl.theta_done)")
    ap.add_argument("--thetas", type=float, nargs="*", default=[0.7, 0.9, 0.97],
                    help="stricter thresholds to report precision at, from the same rollouts")
    ap.add_argument("--strip", type=Path, default=None,
                    help="write a frame strip: per environment with an imagined done, the imagined frames over the replayed ones")
    ap.add_argument("--every", type=int, default=4, help="strip: one frame every this many policy steps")
    ap.add_argument("--strip-rows", type=int, default=6, help="strip: environments shown (those with an imagined done first)")
    ap.add_argument("--gripper", action="store_true",
                    help="per environment, the gripper opening (cm) the world model imagined (its proprioception head) "
                         "beside the replay's, every --every steps up to the imagined done")
    ap.add_argument("--guard", action="store_true",
                    help="apply the rl artifact's guard.pt (rl.guard): an imagined success then needs its confirmation, "
                         "as in the guarded env; the done head alone is printed beside it")
    add_decoding_options(ap)
    add_wm_net_option(ap)
    ap.add_argument("--seed", type=int, default=2_000_000)
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.rl.imagined import (TCP_ERROR_STEPS, imagine_and_replay, precision_at, precision_head_only, tcp_error_at,
                                    tcp_gap_by_outcome, tcp_gap_to_done, token_accuracy_at)
    from stages.sft.policy import POLICY_FILE

    path = {"ppo": args.rl / "policy.zip", "sft": args.sft / POLICY_FILE}.get(args.policy, args.rl / args.policy)
    c = load_check(args.collect, args.tokenize, args.train_wm, args.sft, path, split=args.split, envs=args.envs,
                   steps=args.steps, decode_steps=args.decode_steps, temperature=args.temperature, wm_play=args.wm_play,
                   wm_net=args.wm_net)
    tok, obs_fn, wm, policy, specs, sim = c.tok, c.obs_fn, c.wm, c.policy, c.specs, c.sim
    record = {} if (args.strip or args.gripper) else None
    guard = load_guard(args.rl / "guard.pt", args.theta) if args.guard else None
    try:
        rows = imagine_and_replay(policy, wm, tok, obs_fn, sim, specs, [args.seed + i for i in range(len(specs))],
                                  args.steps, args.theta, record=record, guard=guard)
    finally:
        sim.close()
    if args.strip:
        write_strip(rows, record, tok, args.strip, args.every, args.strip_rows)
    print(f"policy {args.policy}: {len(rows)} {args.split.upper()} environments, horizon {args.steps} policy steps")
    print(f"  replayed actions succeed anywhere in the horizon: {sum(r.first_success > 0 for r in rows)}")
    for theta in [args.theta] + [t for t in args.thetas if t > args.theta]:
        m = precision_at(rows, theta)
        line = f"  theta {theta:.2f}: imagined done {m['imagined_done']}, replayed success {m['replayed_success']}, both {m['imagined_and_replayed']}"
        if m["precision"] is not None:
            line += f", precision {m['precision']:.2f} [{m['precision_lo']:.2f}, {m['precision_hi']:.2f}]"
        print(line)
    if guard is not None:
        m = precision_head_only(rows, args.theta)
        print(f"  the done head alone (no guard veto): imagined done {m['imagined_done']}, both {m['imagined_and_replayed']}"
              + (f", precision {m['precision']:.2f} [{m['precision_lo']:.2f}, {m['precision_hi']:.2f}]"
                 if m["precision"] is not None else ""))
    errs = tcp_error_at(rows, TCP_ERROR_STEPS)
    print("  imagined vs replayed TCP (same actions), mean over environments: "
          + ", ".join(f"{100 * e:.1f} cm after {k}" if e is not None else f"- after {k}" for k, e in errs.items()))
    accs = token_accuracy_at(rows, TCP_ERROR_STEPS)
    print("  tokens of the imagined frame equal to the replayed frame's (the first frame's in brackets): "
          + ", ".join(f"{a[0]:.3f} ({a[1]:.3f}) after {k}" if a is not None else f"- after {k}" for k, a in accs.items()))
    gaps = tcp_gap_by_outcome(rows)
    if gaps["true"] or gaps["false"]:
        print("  largest imagined-vs-replayed TCP gap up to the imagined done (cm), imagined successes the replay "
              + "; ".join(f"{k} ({len(v)}): " + (", ".join(f"{100 * g:.1f}" for g in v) or "-")
                          for k, v in (("confirmed", gaps["true"]), ("did not confirm", gaps["false"]))))
    for r in rows:
        gap = tcp_gap_to_done(r)
        print(f"    {r.env_id:55s} done_at {r.done_at:3d}  peak p {max(r.done_probs):.3f}  replay success {r.success}"
              f" (first at {r.first_success})" + (f"  TCP gap to done {100 * gap:.1f} cm" if gap is not None else ""))
    if args.gripper:
        print_gripper(rows, record, args.every)


def print_gripper(rows, record: dict, every: int) -> None:
    """Imagined vs replayed gripper opening (cm; the proprioception's last entry) per environment.

    A real grasp leaves the closed fingers on the object (an opening of its width), a missed one
    closes them on nothing (~0): does the imagined proprioception tell the two apart where the
    imagined frames do not?"""
    print("  gripper opening (cm), imagined / replayed, every %d steps up to the imagined done (or the end):" % every)
    for i, r in enumerate(rows):
        imagined = record["proprio"][i, :, -1]  # (T,) after steps 1..T
        replayed = [p[-1] for p in record["replay_proprio"][i]]  # after steps 1.. until the replay ended
        end = r.done_at if r.done_at > 0 else len(imagined)
        pairs = [f"{imagined[t]:.1f}/" + (f"{replayed[t]:.1f}" if t < len(replayed) else "-")
                 for t in range(every - 1, end, every)]
        tag = "no imagined done" if r.done_at < 0 else ("confirmed" if r.success else "FALSE")
        print(f"    {r.env_id.split('/')[0]:12s} {tag:16s} min imagined {imagined[:end].min():.1f}, "
              f"min replayed {min(replayed[:end]) if replayed else float('nan'):.1f}: " + " ".join(pairs))


def load_guard(path: Path, theta: float):
    """The guard an rl artifact saved (``guard.pt``: the ensemble's state dict), as the env applies it."""
    from stages.rl.guard import DoneEnsemble, Guard

    if not path.is_file():
        raise SystemExit(f"{path} is missing: was the rl artifact trained with rl.guard=true?")
    state = torch.load(path, map_location="cpu")
    heads = len({k.split(".")[1] for k in state if k.startswith("heads.")})
    ensemble = DoneEnsemble(state["heads.0.0.weight"].shape[0], heads)  # heads.<k>.0 is each head's LayerNorm(dim)
    ensemble.load_state_dict(state)
    return Guard(ensemble.eval(), coef=0.0, theta=theta)  # only the confirmation is read here


def write_strip(rows, record: dict, tok, path: Path, every: int, max_envs: int) -> None:
    """Imagined (decoded) over replayed third-view frames, up to a few steps past the imagined done."""
    from stages.goals.figure import goal_grid, to_uint8

    order = sorted(range(len(rows)), key=lambda i: rows[i].done_at < 0)[:max_envs]  # imagined dones first
    last = max((rows[i].done_at if rows[i].done_at > 0 else 20) for i in order) + every
    shown = list(range(0, min(last, record["tokens"].shape[1] - 1) + 1, every))
    grid = []
    for i in order:
        r = rows[i]
        third, _ = tok.decode(record["tokens"][i, shown])  # (S, 3, H, W) in [0, 1]
        frames = record["frames"][i]
        grid.append((f"{r.env_id.split('/')[0]} imagined (done@{r.done_at})", [to_uint8(f) for f in third]))
        grid.append((f"replayed (success@{r.first_success})", [frames[t] if t < len(frames) else None for t in shown]))
    goal_grid(grid, [f"t={t}" for t in shown], path, max_rows=len(grid))
    print(f"strip: {path}")


if __name__ == "__main__":
    main()
