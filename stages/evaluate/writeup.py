"""Turn evaluated episodes into metrics, tables, figures, GIFs and the report."""
from __future__ import annotations

import json

import numpy as np
import torch

from stages.evaluate.episodes import REST_ACTION, REST_STEPS
from stages.evaluate.report import (SPLIT_NAMES, html_table, image_section, markdown_table, plot_success_vs_time,
                                    strip_figure, success_table, tally, write_gif, write_report)
from stages.evaluate.shipped import acceptance_metrics, acceptance_section, read_acceptance, shipped_label
from stages.evaluate.stats import fmt_rate, wilson

METHODS = {
    "rule": "PPO in ManiSkill (rule reward: success alone)",
    "rule_dense": "PPO in ManiSkill (rule reward: the task's dense reward)",
    "wm": "PPO in world model (WM reward, ours)",
    "embedding": "PPO in world model (embedding reward head)",
    "proxy": "PPO in world model (proxy reward model)",
    "rule_fbc": "Filtered BC in ManiSkill (its own successes imitated)",
    "wm_fbc": "Filtered BC in world model (its done-head successes imitated)",
    "rule_fbc_random": "Filtered BC control in ManiSkill (random own episodes imitated)",
    "wm_fbc_random": "Filtered BC control in world model (random own episodes imitated)",
    "rule_fbc_none": "Filtered BC control in ManiSkill (demonstrations alone refitted)",
    "wm_fbc_none": "Filtered BC control in world model (demonstrations alone refitted)",
    "wm_gated": "PPO in world model (WM reward, ours), calibration-gated tasks",
    "embedding_gated": "PPO in world model (embedding reward head), calibration-gated tasks",
    "proxy_gated": "PPO in world model (proxy reward model), calibration-gated tasks",
}
# PPO in the world model's options that change what it trains on, as stages.rl.method_of suffixes them
VARIANTS = {"_branched": "episodes branched from mid-demonstration frames",
            "_ibc": "after behaviour cloning on imagined demonstrations"}
for _base in ("wm", "embedding", "proxy", "wm_gated", "embedding_gated", "proxy_gated"):
    for _suffix in ("_branched", "_ibc", "_branched_ibc"):
        METHODS[_base + _suffix] = ", ".join([METHODS[_base], *[VARIANTS[v] for v in VARIANTS if v in _suffix]])
# either algorithm in the world model with rl.done_persist > 1
for _label in [m for m in METHODS if not m.startswith("rule")]:
    METHODS[_label + "_persist"] = METHODS[_label] + ", success held for several imagined steps"


def method_label(policy: str, method: str) -> str:
    """A table row's name: SFT, or the rl stage's method (``stages.rl.method_of``)."""
    return "Supervised finetune (SFT)" if policy == "sft" else METHODS[method]


def write_everything(ctx, cfg, facts: dict, results: list[dict]) -> dict:
    out = ctx.out
    method, tasks = facts["method"], list(facts["tasks"])
    main = [r for r in results if "@" not in r["policy"]]
    counts = tally(main)
    metrics: dict = {"method": method, "tasks": tasks, "episodes_per_cell": cfg.episodes, "max_steps": cfg.max_steps,
                     "frame_skip": int(facts["frame_skip"]),
                     "extra_scenes": len(cfg.extra_scenes)}
    for (policy, task, split), (k, n) in sorted(counts.items()):
        p, lo, hi = wilson(k, n)
        base = f"success/{policy}/{task}/{split}"
        metrics.update({base: p, f"{base}_lo": lo, f"{base}_hi": hi, f"{base}_n": n})

    acceptance = read_acceptance(ctx.input("rl"))  # None unless the rl stage ran its acceptance test
    metrics.update(acceptance_metrics(acceptance))
    splits = [s for s in cfg.splits if any(k[2] == s for k in counts)]
    rows = [(method_label(p, method) if p == "sft" else shipped_label(method_label(p, method), acceptance), p)
            for p in cfg.policies]
    header, body = success_table(counts, rows, tasks, splits)
    table_name = "Table 1 layout: success rate in the simulator" if len(tasks) == 1 else \
        f"Table 2 layout: one multi-task policy ({', '.join(tasks)})"
    note = (f"Success rate [95% Wilson interval] (successes/episodes); {cfg.episodes} episodes per task and split, "
            f"horizon {cfg.max_steps} policy steps of {facts['frame_skip']} control steps each, "
            f"ManiSkill's own success check. IND: the training scenes with new initial "
            f"states; OOD: held-out scenes (unseen objects, unseen object-container pairs); extra: user-added scenes.")
    sections = [(table_name, note + "\n\n" + markdown_table(header, body), f"<p>{note}</p>" + html_table(header, body))]
    if acceptance is not None:
        sections.append(("Acceptance test before shipping (rl.accept_episodes)", *acceptance_section(acceptance)))
    rest = came_to_rest(main)
    for (policy, split, outcome), (k, n) in sorted(rest.items()):
        metrics[f"rest/{policy}/{split}/{outcome}"] = k / n
        metrics[f"rest/{policy}/{split}/{outcome}_n"] = n
    if rest:
        sections.append(("How episodes end: came to rest", *rest_section(rest, {p: label for label, p in rows})))

    # Fig. 2: success vs training wall time (SFT at 0 s, then each PPO snapshot)
    snaps = json.loads((ctx.input("rl") / "snapshots" / "index.json").read_text()) \
        if (ctx.input("rl") / "snapshots" / "index.json").is_file() else []
    wall = {f"ppo@{s['timesteps']}": s["wall_seconds"] for s in snaps}
    snap_counts = tally([r for r in results if "@" in r["policy"]])
    pts: dict[str, list] = {"ind": [], "ood": []}
    for split in pts:
        if ("sft", "all", split) in counts:
            pts[split].append((0.0, *counts[("sft", "all", split)]))
        for label, t in wall.items():
            if (label, "all", split) in snap_counts:
                pts[split].append((t, *snap_counts[(label, "all", split)]))
                k, n = snap_counts[(label, "all", split)]
                metrics[f"snapshots/{label}/{split}"] = k / n
    figs = []
    if any(len(v) > 1 for v in pts.values()):
        plot_success_vs_time(pts, out / "success_vs_time.png", f"{METHODS[method]}: success vs training time")
        figs.append("success_vs_time.png")
    if figs:
        sections.append(("Success vs training wall time (Fig. 2)", *image_section(figs)))
    for name, title in (("reward_diagnostics.png", "Reward along held-out successful episodes (Fig. 3)"),
                        ("training.png", "PPO training curve")):
        if (ctx.input("rl") / name).is_file():
            sections.append((title, *image_section([name])))

    # Figs. 4-5: the first IND and the first OOD rollout of each task per policy, as GIFs and one strip figure
    gifs, strips = [], []
    for r in main:
        if "frames" in r:
            name = f"rollout_{r['policy']}_{r['split']}_{r['task']}.gif"
            write_gif(r["frames"], out / name)
            cap = (f"{method_label(r['policy'], method)}, {SPLIT_NAMES[r['split']]}: {r['instruction']} "
                   f"({'success' if r['success'] else 'failure'}, {r['steps']} steps)")
            gifs.append((name, cap))
            idx = np.linspace(0, len(r["frames"]) - 1, min(8, len(r["frames"]))).round().astype(int)  # (<= 8,)
            strips.append((cap, r["frames"][idx]))  # (<= 8, H, W, 3) evenly spaced control steps
    if gifs:
        strip_figure(strips, out / "rollouts.png", "every recorded episode: 8 evenly spaced frames (third view)")
        md = "\n\n".join(f"{cap}\n\n![{n}]({n})" for n, cap in [("rollouts.png", "All of them at a glance"), *gifs])
        hb = "".join(f"<figure><img src='{n}'><figcaption>{cap}</figcaption></figure>"
                     for n, cap in [("rollouts.png", "All of them at a glance"), *gifs])
        sections.append(("Rollouts in the simulator, the first episode of each task (Figs. 4-5)", md, hb))

    extreme = _extreme_actions(ctx, out) if cfg.world_model_figure else None
    if extreme:
        sections.append(("The action world model under extreme actions (Fig. 9)", *image_section([extreme])))
    write_report(out, f"RoboScape-R evaluation: {METHODS[method]}", sections)
    return metrics


def came_to_rest(results: list[dict]) -> dict[tuple[str, str, str], tuple[int, int]]:
    """(policy, split, "failed" | "succeeded") -> (episodes that came to rest, episodes): the policy
    commanded rest (``episodes.longest_rest``) for ``REST_STEPS`` steps running at least once."""
    out: dict[tuple[str, str, str], list[int]] = {}
    for r in results:
        if "rest_steps" in r:
            k = out.setdefault((r["policy"], r["split"], "succeeded" if r["success"] else "failed"), [0, 0])
            k[0] += int(r["rest_steps"] >= REST_STEPS)
            k[1] += 1
    return {key: (v[0], v[1]) for key, v in out.items()}


def rest_section(rest: dict, labels: dict[str, str]) -> tuple[str, str]:
    """The report's table of ``came_to_rest``: per policy and split, failed and successful episodes."""
    keys = sorted({(p, s) for p, s, _ in rest})
    header = ["method", "split", "failed episodes that came to rest", "successful episodes that came to rest"]
    cell = lambda key: fmt_rate(*rest[key]) if key in rest else "-"  # noqa: E731
    body = [[labels.get(p, p), SPLIT_NAMES[s], cell((p, s, "failed")), cell((p, s, "succeeded"))] for p, s in keys]
    note = (f"An episode came to rest when the policy commanded a TCP displacement below {REST_ACTION} (action "
            f"units) for {REST_STEPS} policy steps running: it stopped acting. A failure that came to rest is a "
            "policy that stopped short of success, not one that wandered off.")
    return note + "\n\n" + markdown_table(header, body), f"<p>{note}</p>" + html_table(header, body)


@torch.no_grad()
def _extreme_actions(ctx, out, steps: int = 8) -> str | None:
    """Rows: true actions, zero, and +-10x the data's action bound, from one held-out start frame."""
    from stages.collect.dataset import Dataset
    from stages.common.frame_skip import compose_actions
    from stages.tokenize.store import TokenStore
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.rollout import load_world_model

    split = json.loads((ctx.input("train_wm") / "split.json").read_text())
    ids = split["heldout"] or split["train"]
    ds = Dataset(ctx.input("collect"))
    wm = load_world_model(ctx.input("train_wm"), "action", ctx.device)
    k = wm.spec.frame_skip
    ep_id = next((i for i in ids if ds.load(i).action.shape[0] >= steps * k), None)
    if ep_id is None:
        return None
    tok = load_tokenizer(ctx.input("tokenize"), ctx.device)
    tokens = np.asarray(TokenStore(ctx.input("tokenize")).episode(ep_id), dtype=np.int64)
    true = torch.as_tensor(compose_actions(ds.load(ep_id).action, k)[:steps])
    bound = torch.maximum(wm.net.action_high.abs(), wm.net.action_low.abs()).cpu()
    plans = {"true actions": true, "zero": torch.zeros_like(true), "+10x bound": (10 * bound).expand_as(true).clone(),
             "-10x bound": (-10 * bound).expand_as(true).clone()}
    rows = []
    for label, actions in plans.items():
        roll = wm.rollout(1)
        roll.reset(torch.as_tensor(tokens[:1]))
        frames = [tokens[0]]
        for t in range(steps):
            frames.append(roll.step(actions[t : t + 1].to(ctx.device)).tokens[0].cpu().numpy())
        third, _ = tok.decode(torch.as_tensor(np.stack(frames)))
        rows.append((label, (third.clamp(0, 1).permute(0, 2, 3, 1).cpu().numpy() * 255).round().astype(np.uint8)))
    strip_figure(rows, out / "extreme_actions.png", "action WM rollouts from one held-out frame (clipped to the data range)")
    return "extreme_actions.png"
