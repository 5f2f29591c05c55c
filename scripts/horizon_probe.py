"""Does the world model show the SFT policy succeeding when the success is k policy steps away?

The rl stage's calibration gate imagines the SFT policy for the whole horizon from first frames, and on
the two-round DAgger SFT it keeps pull alone: the tasks it drops (pick and place, move to aim) are the
ones whose real successes come late (median 25-30 policy steps against 11-13 for push and pull,
docs/RESULTS.md, session 95). This probe asks whether that is the distance: for each task, it starts
the same policy (deterministic actions) on its own imagined frames at the world-model frame ``k`` steps
before the first successful frame of an IND training demonstration that succeeded (the frame's
tokens and the robot's recorded proprioception, ``RLInputs.starts(any_frame=True)``), imagines
``k + --slack`` steps in the action world model (wm_play's fine-tuned one, as the rl stage does) and
counts the starts where the done head reached ``--theta``. No simulator runs: a demonstration reached
success from there in ``k`` steps, so a high rate says the model can show this policy finishing
from there, a low one that it cannot even this close. ``--actions demo`` replays the demonstration's
own recorded actions from the same frames instead (``k`` of them, then its last one repeated for the
slack): whether the model and its done head show the success when the actions are the ones that
really reached it, which separates the policy's imagined behaviour from the model's picture of the
task's end. ``--actions sim`` asks what the policy really does from there: each demonstration's
simulator state at that frame is restored (reset with the episode's seed, its recorded control
actions replayed, as collect's replay check does), the same policy acts in ManiSkill for ``k +
--slack`` policy steps, and the actions it took there are then imagined open loop from the frame.
Per start it reports the real success, the world model's verdict on the policy's real actions (open
loop) and on the policy acting on its own imagined frames (closed loop, the default mode), and how
far the restored state is from the recorded one (TCP and object, mm; tokens of the rendered frame
equal to the recorded frame's).

    PYTHONPATH=. .venv/bin/python scripts/horizon_probe.py <collect> <tokenize> <train_wm> <goals> <sft> \\
        <wm_play> [--k 5 10 20 30] [--actions policy|demo|sim] [--policy FILE] [--per-task 32] [--slack 10] [--theta 0.5] [--seed 0] [--out probe.json]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

STAGES = ("collect", "tokenize", "train_wm", "goals", "sft", "wm_play")


def start_k_before(starts: list, k: int):
    """The start ``k`` frames before the first successful one, of one episode's starts before success
    (``starts[j]`` is frame j, the list ends just before the success), or None if it has fewer."""
    return starts[-k] if 1 <= k <= len(starts) else None


def demo_actions(actions: np.ndarray, start: int, steps: int) -> np.ndarray:
    """(steps, 7) the recorded world-model actions from frame ``start`` on (``actions`` (T', 7)), the last
    one repeated where the episode ends first."""
    a = actions[start:start + steps]
    return np.concatenate([a, np.repeat(a[-1:], steps - len(a), axis=0)]) if len(a) < steps else a


def probe_inputs(dirs: dict, policy_file: Path | None = None):
    """The rl stage's inputs over the artifact directories ``dirs`` (CPU), with the policy of ``policy_file``
    instead of the sft artifact's when given (it must observe as that policy does), set to act deterministically."""
    from stages.rl import Config
    from stages.rl.inputs import RLInputs

    inp = RLInputs.load(SimpleNamespace(input=lambda name: dirs[name], device="cpu"), Config())
    if policy_file is not None:
        from stages.sft.policy import load_policy

        inp = dataclasses.replace(inp, sft_policy=load_policy(policy_file))
    inp.sft_policy.set_training_mode(False)  # deterministic actions, as the gate
    return inp


def successful_demos(inp, task: str, n: int, rng: np.random.Generator) -> list:
    """Up to ``n`` (environment, episode id) of ``task``'s successful IND training demonstrations (a choice by ``rng``)."""
    train = set(inp.split["train"])
    demos = [(e, i) for e in inp.envs if e.task == task and e.split == "ind" for i in e.episodes
             if i in train and inp.meta[i].success]
    return [demos[j] for j in sorted(rng.choice(len(demos), size=min(n, len(demos)), replace=False))]


def sim_by_env(inp, collect_dir: Path, max_steps: int, seed: int):
    """(a ``SimTaskEnv`` over every environment of ``inp``, their ``SimSpec`` by environment id)."""
    from stages.common.sim_env import sim_over

    sim, spec_list = sim_over(collect_dir, inp.obs_fn, inp.envs, max_steps=max_steps, frame_skip=inp.frame_skip, seed=seed)
    return sim, {e.env_id: sp for e, sp in zip(inp.envs, spec_list)}


def restore(sim, spec, seed: int, control_actions: np.ndarray) -> dict:
    """Put ``sim`` (a ``SimTaskEnv``) in a recorded episode's state after ``control_actions`` (c, 7): reset
    ``spec``'s scene with the episode's ``seed`` and step the actions unrendered (collect recorded them
    from that reset, and its replay check reproduces them). Returns the policy's observation there; the
    episode's first frame is the reset's."""
    env = sim._env_for(spec)
    raw, _ = env.reset(seed=int(seed))
    sim.spec_now, sim.env, sim.t, sim.frames = spec, env, 0, []
    sim.instruction = spec.instruction or env.instruction
    obs = sim._observe(raw, first=True)
    if len(control_actions) == 0:
        return obs
    for a in control_actions:
        sim._unobserved_control_step(np.asarray(a, np.float32))
    raw, _, _, _ = sim._observe_current(np.asarray(control_actions[-1], np.float32))
    return sim._observe(raw)


def restore_error(sim, ee_pose: np.ndarray, obj_pose: np.ndarray | None) -> tuple[float, float]:
    """(TCP, object) position error in mm of the simulator's current state against the recorded
    ``ee_pose`` (7,) and ``obj_pose`` (7,) (nan where the shard has no object pose)."""
    base = sim.env.unwrapped
    tcp = float(np.linalg.norm(base.agent.tcp.pose.p[0].cpu().numpy() - ee_pose[:3])) * 1000
    obj = float("nan") if obj_pose is None else float(np.linalg.norm(base.obj.pose.p[0].cpu().numpy() - obj_pose[:3])) * 1000
    return tcp, obj


def policy_in_sim(policy, sim, obs: dict, steps: int) -> tuple[bool, np.ndarray]:
    """Run ``policy`` (deterministic) in ``sim`` from ``obs`` for at most ``steps`` policy steps: (success,
    the executed actions (n, 7), n <= steps, ending at the success)."""
    from stages.sft.policy import act

    sim.max_steps, sim.t = steps, 0
    taken = []
    for _ in range(steps):
        a = act(policy, {k: v[None] for k, v in obs.items()})[0]  # (7,)
        taken.append(a)
        obs, _, success, truncated, _ = sim.step(a)
        if success:
            return True, np.stack(taken)
        if truncated:
            break
    return False, np.stack(taken)


@torch.no_grad()
def replayed_successes(wm, tokens: np.ndarray, actions: np.ndarray, theta: float) -> np.ndarray:
    """(N,) bool: whether the done head reached ``theta`` while the world model imagined the recorded
    ``actions`` (N, T, 7) from ``tokens`` (N, h, w)."""
    roll = wm.rollout(len(tokens))
    roll.reset(torch.as_tensor(tokens).long().to(wm.device))
    done = np.zeros(len(tokens), bool)
    for t in range(actions.shape[1]):
        a = torch.as_tensor(actions[:, t], dtype=torch.float32, device=wm.device)
        a = torch.minimum(torch.maximum(a, wm.net.action_low), wm.net.action_high)  # as the rl env clips
        done |= roll.step(a).done_prob.float().cpu().numpy() >= theta
    return done


def sim_row(inp, sim, specs: dict, near: list, starts: list, task: str, k: int, args) -> dict:
    """``--actions sim`` for one (task, k): ``near`` [(environment, episode id, its starts)], ``starts`` the
    world-model starts k frames before each success."""
    from stages.common.frame_skip import frame_indices
    from stages.rl.calibration import imagined_successes

    steps = k + args.slack
    real, acts, tcp, obj, match = [], [], [], [], []
    for (e, i, st), s in zip(near, starts):
        ep = inp.dataset.load_states(i)
        c = int(frame_indices(len(ep["action"]), inp.frame_skip)[len(st) - k])  # control step of the start frame
        obs = restore(sim, specs[e.env_id], inp.meta[i].seed, ep["action"][:c])
        t, o = restore_error(sim, ep["ee_pose"][c], ep["obj_pose"][c] if "obj_pose" in ep else None)
        tcp.append(t)
        obj.append(o)
        match.append(float((sim.tokens[0].numpy() == s.tokens).mean()))
        ok, taken = policy_in_sim(inp.sft_policy, sim, obs, steps)
        real.append(ok)
        acts.append(demo_actions(taken, 0, steps))  # (steps, 7): after the end, its last action repeated
    real = np.asarray(real)
    wm_open = replayed_successes(inp.wm, np.stack([s.tokens for s in starts]), np.stack(acts), args.theta)
    wm_closed = imagined_successes(inp.sft_policy, inp.wm, inp.obs_fn, starts, steps, args.theta)
    row = {"task": task, "k": k, "starts": len(starts), "real": int(real.sum()), "wm_open": int(wm_open.sum()),
           "wm_closed": int(wm_closed.sum()), "wm_open_of_real": int((wm_open & real).sum()),
           "wm_closed_of_real": int((wm_closed & real).sum()), "tcp_mm_median": float(np.median(tcp)),
           "obj_mm_median": float(np.nanmedian(obj)), "obj_mm_max": float(np.nanmax(obj)),
           "token_match_median": float(np.median(match))}
    print(f"{task:12s} k={k:3d} (sim): real {row['real']}/{len(starts)}; world model on the policy's real actions "
          f"{row['wm_open']} ({row['wm_open_of_real']} of the real), closed loop {row['wm_closed']} "
          f"({row['wm_closed_of_real']} of the real); restored TCP {row['tcp_mm_median']:.1f} mm, object "
          f"{row['obj_mm_median']:.1f} mm (max {row['obj_mm_max']:.1f}), tokens equal {row['token_match_median']:.2f}",
          flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for name in STAGES:
        ap.add_argument(name, type=Path, help=f"a committed {name} artifact directory")
    ap.add_argument("--k", type=int, nargs="+", default=[5, 10, 20, 30], help="policy steps before the success")
    ap.add_argument("--actions", choices=["policy", "demo", "sim"], default="policy",
                    help="the SFT policy closed loop (default), the demonstration's recorded actions, or the "
                         "policy in ManiSkill from the demonstration's restored state (module docstring)")
    ap.add_argument("--per-task", type=int, default=32, help="demonstrations per task (a seeded choice)")
    ap.add_argument("--slack", type=int, default=10, help="imagined steps beyond k")
    ap.add_argument("--theta", type=float, default=0.5, help="done-head threshold (rl.theta_done)")
    ap.add_argument("--policy", type=Path, default=None,
                    help="probe this policy file (an rl artifact's policy.zip, a snapshot, imagined_bc_policy.zip) "
                         "instead of the sft artifact's; it must observe as that sft policy does")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="write the table as JSON here")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.rl.calibration import imagined_successes

    dirs = {name: getattr(args, name) for name in STAGES}
    inp = probe_inputs(dirs, args.policy)
    rng = np.random.default_rng(args.seed)
    sim = specs = None
    if args.actions == "sim":
        sim, specs = sim_by_env(inp, dirs["collect"], 1, args.seed)
    rows = []
    for task in inp.tasks:
        pick = successful_demos(inp, task, args.per_task, rng)
        # one episode's starts before its success: an Environment holding that episode alone
        per_episode = [inp.starts([dataclasses.replace(e, episodes=[i])], any_frame=True) for e, i in pick]
        for k in args.k:
            starts = [s for s in (start_k_before(st, k) for st in per_episode) if s is not None]
            if not starts:
                done = np.zeros(0, bool)
            elif args.actions == "sim":
                near = [(e, i, st) for (e, i), st in zip(pick, per_episode) if start_k_before(st, k) is not None]
                rows.append(sim_row(inp, sim, specs, near, starts, task, k, args))
                continue
            elif args.actions == "policy":
                done = imagined_successes(inp.sft_policy, inp.wm, inp.obs_fn, starts, k + args.slack, args.theta)
            else:
                near = [(i, st) for (_, i), st in zip(pick, per_episode) if start_k_before(st, k) is not None]
                acts = np.stack([demo_actions(inp.steps(i)[1], len(st) - k, k + args.slack)  # (N, k + slack, 7)
                                 for i, st in near])
                done = replayed_successes(inp.wm, np.stack([s.tokens for s in starts]), acts, args.theta)
            rows.append({"task": task, "k": k, "starts": len(starts), "imagined": int(done.sum()),
                         "rate": float(done.mean()) if len(done) else None})
            print(f"{task:12s} k={k:3d} ({args.actions}): imagined success {int(done.sum())}/{len(starts)} within {k + args.slack} steps",
                  flush=True)
    if args.out:
        keys = {name: dirs[name].name[:12] for name in STAGES}  # the artifacts' keys, not this machine's paths
        opts = {k: getattr(args, k) for k in ("k", "actions", "per_task", "slack", "theta", "seed")}
        opts["policy"] = None if args.policy is None else f"{args.policy.parent.name[:12]}/{args.policy.name}"
        args.out.write_text(json.dumps({"artifacts": keys, "options": opts, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
