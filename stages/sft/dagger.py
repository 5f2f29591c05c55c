"""DAgger with the planner as the expert: demonstrations that continue from the policy's own states.

The cloned policy fails mostly by stopping (the evaluate stage's "came to rest") in states its
demonstrations never pass through; the planner, handed the simulator there, finishes most of them
(docs/sft.md, "DAgger with the planner as the expert"). One round: the policy (deterministic
actions) acts in ``episodes`` fresh starts of the IND training environments for at most
``max_steps`` policy steps; an episode that has not succeeded when the policy comes to rest
(``REST_STEPS`` steps running below ``REST_ACTION``) or at its last step is handed to the planner
(``stages.common.takeover``), and a continuation that succeeds becomes a demonstration from that
state on, read as the sft stage reads the collected ones (frame skip, re-timing; frames encoded by the
tokenizer). The policy's own steps before the takeover are never imitated, as a recovery episode's
mistake is not.

Starts: reset seeds ``DAGGER_SEED + 100,000 x sft.seed + 10,000 x round + i``, apart from collection
(< 10^6 plus the recovery offset 5 x 10^6), evaluation (10^6 + ...), the rl stage's checks (3-4 x 10^6)
and the play (5 x 10^6 + ...), so no evaluated state is ever a DAgger start.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from stages.common.proprio import proprio_from_state
from stages.sft.data import Demo, compose_between, retimed_indices

DAGGER_SEED = 6_000_000


@dataclass
class Rollout:
    """One DAgger start: how the policy's episode ended and what the planner made of it."""

    env_id: str
    seed: int
    policy_steps: int
    policy_success: bool
    rested: bool  # the policy came to rest (the takeover began there) rather than running out of steps
    takeover: str  # "none" (the policy succeeded), "success", "failed" or "no_plan"
    control_steps: int = 0  # length of the planner's continuation
    pairs: int = 0  # (observation, action) pairs the demonstration adds


def round_seeds(seed: int, round_: int, n: int) -> list[int]:
    """Reset seeds of round ``round_``'s ``n`` starts (module docstring)."""
    base = DAGGER_SEED + 100_000 * seed + 10_000 * round_
    return [base + i for i in range(n)]


def demo_from_recording(rec, tokenizer, episode_id: str, instruction: str, frame_skip: int, min_move: float,
                        max_gap: int, first: np.ndarray | None = None) -> Demo:
    """The planner's continuation as a demonstration at policy steps (``stages.sft.data.load_demo``'s
    reading: re-timed when ``min_move > 0``, else every ``frame_skip``-th frame); only the kept
    frames are encoded. ``first`` (h, w): the episode's first frame's tokens (a policy that reads
    the first frame reads the rollout's, not the takeover state's)."""
    from stages.common.frame_skip import compose_actions, frame_indices

    n = len(rec.action)
    if min_move > 0:
        idx = retimed_indices(rec.ee_pose[:, :3], rec.action[:, 6], frame_skip, min_move, max_gap)
        actions = compose_between(rec.action, idx, frame_skip)
    else:
        idx = frame_indices(n, frame_skip)
        actions = compose_actions(rec.action, frame_skip)
    tokens = tokenizer.encode(rec.third[idx], rec.wrist[idx]).cpu().numpy().astype(np.int64)  # (T'+1, h, w)
    return Demo(episode_id, instruction, tokens, proprio_from_state(rec.ee_pose[idx], rec.qpos[idx]), actions,
                rec.obj_pose[idx, :3], first)


def run_round(policy, sim, specs: list, seeds: list[int], *, max_steps: int, plan_steps: int, frame_skip: int,
              min_move: float, max_gap: int, progress=None, on_takeover=None) -> tuple[list[Demo], list[Rollout]]:
    """One DAgger round over ``specs[i]`` reset with ``seeds[i]`` in ``sim`` (a ``SimTaskEnv`` stepping
    ``frame_skip`` control steps per action): the new demonstrations and one ``Rollout`` per start.
    ``on_takeover(row, takeover)``, if given, sees every takeover (``scripts/dagger_strips.py`` draws them)."""
    from stages.common.takeover import take_over
    from stages.common.rest import REST_ACTION, REST_STEPS
    from stages.sft.policy import act

    demos, rows = [], []
    for spec, seed in zip(specs, seeds):
        obs, info = sim.reset(seed=seed, options={"spec": spec})
        success, steps, run = bool(info["success"]), 0, 0
        while not success and steps < max_steps and run < REST_STEPS:
            action = act(policy, {k: v[None] for k, v in obs.items()})[0]  # (7,)
            run = run + 1 if np.linalg.norm(action[:3]) < REST_ACTION else 0
            obs, _, success, truncated, _ = sim.step(action)
            steps += 1
            if truncated:
                break
        row = Rollout(spec.key, seed, steps, success, run >= REST_STEPS, "none")
        if not success:
            took = take_over(sim.env.env, plan_steps)  # the ManiSkill env under the observation wrapper
            row.takeover = "no_plan" if took.recording is None else "success" if took.success else "failed"
            if took.recording is not None:
                row.control_steps = len(took.recording.action)
            if took.success:
                demo = demo_from_recording(took.recording, sim.obs_fn.tok, f"dagger/{spec.key}/{seed}", sim.instruction,
                                           frame_skip, min_move, max_gap, sim.first_tokens[0].cpu().numpy())
                row.pairs = len(demo.actions)
                demos.append(demo)
            if on_takeover is not None:
                on_takeover(row, took)
        rows.append(row)
        if progress is not None:
            progress.update(1)
    return demos, rows


def summary(rows: list[Rollout]) -> dict:
    """Counts of one round's starts by outcome (the stage's metrics)."""
    failed = [r for r in rows if not r.policy_success]
    return {"starts": len(rows), "policy_success": len(rows) - len(failed),
            "rested": sum(r.rested for r in failed),
            **{f"takeover_{k}": sum(r.takeover == k for r in failed) for k in ("success", "failed", "no_plan")},
            "pairs": sum(r.pairs for r in rows)}


DEMOS_NPZ, DEMOS_JSON, ROLLOUTS = "demos.npz", "demos.json", "rollouts.jsonl"


def save_demos(path, demos: list[Demo]) -> None:
    """``demos`` into directory ``path`` (``DEMOS_NPZ`` arrays, ``DEMOS_JSON`` ids and instructions)."""
    import json

    arrays = {}
    for i, d in enumerate(demos):
        arrays.update({f"{i}/tokens": d.tokens, f"{i}/proprio": d.proprio, f"{i}/actions": d.actions, f"{i}/obj": d.obj_xyz,
                       f"{i}/first": d.tokens[0] if d.first is None else d.first})
    np.savez(path / DEMOS_NPZ, **arrays)
    (path / DEMOS_JSON).write_text(json.dumps([[d.episode_id, d.instruction] for d in demos]) + "\n")


def load_demos(path) -> list[Demo]:
    """``save_demos``'s demonstrations back."""
    import json

    names = json.loads((path / DEMOS_JSON).read_text())
    with np.load(path / DEMOS_NPZ) as z:
        return [Demo(eid, text, z[f"{i}/tokens"], z[f"{i}/proprio"], z[f"{i}/actions"], z[f"{i}/obj"], z[f"{i}/first"])
                for i, (eid, text) in enumerate(names)]


def save_round(path, demos: list[Demo], rows: list[Rollout]) -> None:
    """One round's demonstrations and rows (``ROLLOUTS``) into directory ``path`` (its checkpoint)."""
    import json

    save_demos(path, demos)
    (path / ROLLOUTS).write_text("".join(json.dumps(asdict(r)) + "\n" for r in rows))


def load_round(path) -> tuple[list[Demo], list[Rollout]]:
    """``save_round``'s demonstrations and rows back."""
    import json

    return load_demos(path), [Rollout(**json.loads(x)) for x in (path / ROLLOUTS).read_text().splitlines()]
