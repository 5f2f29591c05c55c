"""The sweep report: every point's evaluation pooled per method (seeds aggregated), the paper's table
layouts, success vs training wall time, training curves, reward diagnostics, rollouts and extreme
actions. Hooked into ``pipeline.yaml`` as ``sweeps.<name>.report``; it is not a stage, so changing it
changes no stage's cache key (a rerun of ``pipeline sweep`` rewrites the report from cached points).

SFT is its own stage (stages/sft), so points that differ only in the reward module share one SFT
policy: its episodes are counted once per sft artifact, not once per point.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from stages.evaluate.report import html_table, image_section, markdown_table, success_table, tally, write_report
from stages.evaluate.writeup import METHODS
from stages.sweep_report.figures import rollout_strips, success_vs_time, training_curves
from stages.sweep_report.gather import PointRun, gather
from stages.sweep_report.paired import across_seeds, by_split, fmt_across_seeds, fmt_difference, pair_up

ORDER = ["sft", *METHODS]  # table order: the registry's (stages.evaluate.writeup.METHODS)
LABELS = {"sft": "Supervised finetune (SFT)", **METHODS}


def _episodes(runs: list[PointRun], snapshots: bool = False) -> list[dict]:
    """Evaluated episodes relabelled by method (``policy`` = sft or the reward module); SFT once per sft_key."""
    out, sft_seen = [], set()
    for run in runs:
        take_sft = run.sft_key not in sft_seen
        if run.results:
            sft_seen.add(run.sft_key)
        for r in run.results:
            snap = "@" in r["policy"]
            if snap != snapshots or (r["policy"] == "sft" and not take_sft):
                continue
            method = "sft" if r["policy"] == "sft" else run.method
            out.append({**r, "policy": method if not snap else f"{method}@{r['policy'].split('@', 1)[1]}",
                        "point": run.label})
    return out


def _section(title: str, note: str, header: list[str], body: list[list[str]]) -> tuple[str, str, str]:
    md = (note + "\n\n" if note else "") + markdown_table(header, body)
    return title, md, (f"<p>{note}</p>" if note else "") + html_table(header, body)


def _success_sections(runs: list[PointRun]) -> list[tuple[str, str, str]]:
    sections = []
    for single in (True, False):
        group = [r for r in runs if (len(r.tasks) == 1) == single and r.results]
        if not group:
            continue
        eps = _episodes(group)
        counts = tally(eps)
        tasks = list(dict.fromkeys(t for r in group for t in r.tasks))
        methods = [m for m in ORDER if any(k[0] == m for k in counts)]
        splits = [s for s in ("ind", "ood", "extra") if any(k[2] == s for k in counts)]
        header, body = success_table(counts, [(LABELS[m], m) for m in methods], tasks, splits)
        seeds = sorted({str(r.seed) for r in group})
        note = (f"{len(group)} sweep points, rl seeds {', '.join(seeds)}; each method's episodes pooled over its points "
                f"(SFT: once per seed and task set, it does not depend on the reward); success rate [95% Wilson] "
                f"(successes/episodes), ManiSkill's own success check. Every point is evaluated on the same initial "
                f"states, so pooled seeds are different policies on repeated states.")
        title = ("Table 1 layout: one policy per task" if single else
                 f"Table 2 layout: one multi-task policy ({', '.join(tasks)})") + ", seeds pooled"
        sections.append(_section(title, note, header, body))
    return sections


def _pairs_by_method(runs: list[PointRun]) -> tuple[dict[str, list], dict[tuple[str, str], list]]:
    """(PPO episode, SFT success) pairs on shared initial states: per method, and per (method, seed)."""
    paired: dict[str, list] = {}
    per_seed: dict[tuple[str, str], list] = {}
    for run in runs:
        pairs = pair_up([r for r in run.results if r["policy"] == "ppo"], [r for r in run.results if r["policy"] == "sft"])
        paired.setdefault(run.method, []).extend(pairs)
        per_seed.setdefault((run.method, str(run.seed)), []).extend(pairs)
    return paired, per_seed


def _paired_section(runs: list[PointRun]) -> tuple[str, str, str] | None:
    """Each method minus the SFT policy it started from, on the same initial states, per seed and pooled."""
    paired, per_seed = _pairs_by_method(runs)
    if not any(paired.values()):
        return None
    splits = [s for s in ("ind", "ood", "extra") if any(r["split"] == s for v in paired.values() for r, _ in v)]
    header = ["method", "seed"] + [s.upper() for s in splits]
    body = []
    for method in [m for m in ORDER if paired.get(m)]:
        seeds = sorted(seed for m, seed in per_seed if m == method)
        for seed in seeds + (["pooled"] if len(seeds) > 1 else []):
            res = by_split(paired[method] if seed == "pooled" else per_seed[(method, seed)])
            body.append([LABELS[method], seed] + [fmt_difference(res[(s,)]) if (s,) in res else "-" for s in splits])
        if len(seeds) > 1:
            diffs = {s: [r[(s,)]["diff"] for r in (by_split(per_seed[(method, seed)]) for seed in seeds) if (s,) in r]
                     for s in splits}
            body.append([LABELS[method], "across seeds"] + [fmt_across_seeds(across_seeds(diffs[s])) for s in splits])
    note = ("Success of the PPO policy minus success of the SFT policy it started from, episode by episode on the "
            "same initial states (tasks pooled): mean [95% interval of the paired differences]; 'better' / 'worse' "
            "count the states only PPO / only SFT solved. An interval above 0 is an improvement on SFT by these "
            "policies. 'across seeds': the mean of the per-seed differences with a 95% Student-t interval over "
            "the seeds, i.e. what another seed of the method would give; with few seeds it is much wider.")
    return _section("PPO minus SFT, paired on the same initial states", note, header, body)


def _paired_by_task_section(runs: list[PointRun]) -> tuple[str, str, str] | None:
    """Each method minus its SFT policy per task, seeds pooled: where in the task suite it gains or loses."""
    paired, per_seed = _pairs_by_method(runs)
    if not any(paired.values()):
        return None
    keys = ("task", "split")
    splits = [s for s in ("ind", "ood", "extra") if any(r["split"] == s for v in paired.values() for r, _ in v)]
    header = ["method", "task"] + [s.upper() for s in splits] + [f"{s.upper()} across seeds" for s in splits]
    body = []
    for method in [m for m in ORDER if paired.get(m)]:
        pooled = by_split(paired[method], keys)
        seeds = [by_split(per_seed[k], keys) for k in sorted(k for k in per_seed if k[0] == method)]
        for task in dict.fromkeys(r["task"] for r, _ in paired[method]):
            cells = [fmt_difference(pooled[(task, s)]) if (task, s) in pooled else "-" for s in splits]
            spread = [fmt_across_seeds(across_seeds([r[(task, s)]["diff"] for r in seeds if (task, s) in r]))
                      for s in splits]
            body.append([LABELS[method], task] + cells + spread)
    note = ("The paired differences above, per task: PPO minus its own seed's SFT policy on the same initial states, "
            "seeds pooled [95% interval], and the mean of the per-seed differences with its Student-t interval over "
            "seeds. A world model's reward can be informative on some tasks and misleading on others (docs/rl.md, "
            "\"The calibration gate\"); a pooled difference near 0 may hide both.")
    return _section("PPO minus SFT per task, paired", note, header, body)


def _per_run_section(runs: list[PointRun]) -> tuple[str, str, str] | None:
    rows = []
    for m in ORDER:
        for split in ("ind", "ood", "extra"):
            rates = []
            for run in runs:
                policy = "sft" if m == "sft" else "ppo"
                if m != "sft" and run.method != m:
                    continue
                eps = [r for r in run.results if r["policy"] == policy and r["split"] == split]
                if eps:
                    rates.append((run.sft_key if m == "sft" else run.label, np.mean([r["success"] for r in eps])))
            rates = list(dict(rates).values())  # SFT: one rate per sft_key
            if rates:
                rows.append([LABELS[m], split, str(len(rates)), " / ".join(f"{v:.3f}" for v in rates),
                             f"{np.mean(rates):.3f}", f"{np.std(rates, ddof=1):.3f}" if len(rates) > 1 else "-"])
    if not rows:
        return None
    return _section("Per-run success (tasks pooled), mean and sd over runs", "",
                    ["method", "split", "runs", "per run", "mean", "sd over runs"], rows)


def _joined(values: list[float], fmt: str = "{:.0f}") -> str:
    """'741 / 1340': the non-NaN values of one table cell, '-' if none."""
    v = [x for x in values if x == x]
    return " / ".join(fmt.format(x) for x in v) if v else "-"


def _first_last(metrics: list[dict]) -> str:
    """'0.41 -> 0.53 / ...': each run's training success in the first and last fifth of PPO by start step
    ('-' for a run without it: an older artifact, or no episode uncensored)."""
    pairs = [(m.get("ppo/success_first_fifth"), m.get("ppo/success_last_fifth")) for m in metrics]
    cells = [f"{a:.2f} -> {b:.2f}" if a is not None and b is not None else "-" for a, b in pairs]
    return " / ".join(cells) if any(c != "-" for c in cells) else "-"


def _shipped(metrics: list[dict]) -> str:
    """'PPO (+0.03, 600 sim episodes) / SFT (-0.08, 600 sim episodes)': which policy each run shipped after
    its acceptance test, with the test's paired difference and simulator episodes; '-' for a run without
    the test (``rl.accept_episodes`` 0), and '-' alone when no run had it."""
    cells = [f"{'PPO' if m['accept/kept_ppo'] else 'SFT'} ({m['accept/difference']:+.2f}, {m['accept/episodes']} sim episodes)"
             if "accept/kept_ppo" in m else "-" for m in metrics]
    return " / ".join(cells) if any(c != "-" for c in cells) else "-"


def _cost_section(runs: list[PointRun]) -> tuple[str, str, str] | None:
    rows = []
    for m in ORDER[1:]:
        mine = [r for r in runs if r.method == m]
        if not mine:
            continue
        rows.append([LABELS[m], str(len(mine)), _joined([r.seconds.get("wm_play", np.nan) for r in mine]),
                     _joined([r.seconds.get("rl", np.nan) for r in mine]),
                     _joined([r.rl_metrics.get("ppo/seconds", np.nan) for r in mine]),
                     _joined([r.rl_metrics.get("ppo/env_steps_per_second", np.nan) for r in mine], "{:.1f}"),
                     _joined([r.rl_metrics.get("ppo/terminated_fraction", np.nan) for r in mine], "{:.3f}"),
                     _first_last([r.rl_metrics for r in mine]), _shipped([r.rl_metrics for r in mine]),
                     _joined([r.seconds.get("evaluate", np.nan) for r in mine])])
    if not rows:
        return None
    note = ("Wall seconds per run (one value per point, in point order), as the stage manifests recorded them; the "
            "rl stage includes reward heads, diagnostics and the imagined-success check besides PPO; wm_play (the world "
            "model's fine-tune on the SFT policy's play, which every reward point of a seed trains or checks in) is "
            "one run per seed, listed with each of its points. Points may have run two at a time on "
            "the same cores, which inflates these times. Terminated = fraction of PPO training episodes that the "
            "reward's success signal ended (done head or simulator success). Training success, first -> last fifth: "
            "the same success signal in the first and last fifth of PPO's episodes by start step (inside the "
            "world model the done head's verdict, not the simulator's). Shipped: with the rl stage's acceptance "
            "test, whether the run shipped PPO's policy or SFT's weights (then its PPO rows above are SFT's policy), "
            "the test's PPO-minus-SFT difference and the simulator episodes it spent.")
    return _section("Cost per method", note, ["method", "runs", "wm_play s", "rl stage s", "PPO s", "PPO env steps/s",
                                              "terminated", "training success, first -> last fifth", "shipped (acceptance test)",
                                              "evaluate s"], rows)


def _time_curves(runs: list[PointRun]) -> dict[str, dict[str, list[tuple[float, int, int]]]]:
    """method -> split -> [(mean wall s, successes, n)]: SFT at 0, then each PPO snapshot pooled over seeds."""
    curves: dict[str, dict[str, list]] = {}
    sft = tally(_episodes(runs))
    for m in ORDER[1:]:
        mine = [r for r in runs if r.method == m and r.results]
        if not mine:
            continue
        snaps = tally(_episodes(mine, snapshots=True))
        walls: dict[int, list[float]] = {}
        for r in mine:
            for s in r.snapshots:
                walls.setdefault(int(s["timesteps"]), []).append(float(s["wall_seconds"]))
        by_split: dict[str, list] = {}
        for split in ("ind", "ood", "extra"):
            pts = [(0.0, *sft[("sft", "all", split)])] if ("sft", "all", split) in sft else []
            for steps, w in sorted(walls.items()):
                if (f"{m}@{steps}", "all", split) in snaps:
                    pts.append((float(np.mean(w)), *snaps[(f"{m}@{steps}", "all", split)]))
            if len(pts) > 1:
                by_split[split] = pts
        if by_split:
            curves[m] = by_split
    return curves


def _copy(src: Path, out: Path, name: str) -> str | None:
    if not src.is_file():
        return None
    shutil.copyfile(src, out / name)
    return name


def _figure_sections(runs: list[PointRun], out: Path) -> list[tuple[str, str, str]]:
    sections = []
    curves = _time_curves(runs)
    if curves:
        success_vs_time(curves, LABELS, out / "success_vs_time.png")
        md, hb = image_section(["success_vs_time.png"])
        note = ("Snapshots of each PPO run evaluated on a few episodes per split, pooled over seeds; x = PPO wall time "
                "of the snapshot averaged over seeds (the rl stage's fixed costs, SFT and reward heads, excluded).")
        sections.append(("Success vs training wall time (Fig. 2)", note + "\n\n" + md, f"<p>{note}</p>" + hb))
    train = {m: sorted(((str(r.seed), r.training, r.success_by_start) for r in runs if r.method == m), key=lambda x: x[0])
             for m in ORDER[1:]}
    if any(eps for v in train.values() for _, eps, _ in v):
        training_curves(train, LABELS, out / "training_curves.png")
        note = ("Top: episode return in each reward's own units over PPO wall time. Bottom: training success binned by "
                "the step each episode started at (episodes started before the earliest unfinished one; a success ends "
                "early, so binning by end time would start too high). Inside the world model success is the done "
                "head's verdict, not the simulator's: compare it with the imagined-success precision.")
        md, hb = image_section(["training_curves.png"])
        sections.append(("PPO training curves, every run (Fig. 3, left)", note + "\n\n" + md, f"<p>{note}</p>" + hb))
    first = runs[0]
    diag = _copy(first.rl_dir / "reward_diagnostics.png", out, "reward_diagnostics.png")
    if diag:
        note = f"Every reward module along held-out successful episodes, from point {first.label}."
        md, hb = image_section([diag])
        sections.append(("Reward along held-out successful episodes (Fig. 3, right)", note + "\n\n" + md,
                         f"<p>{note}</p>" + hb))
    gifs = []
    for m in ORDER:
        run = next((r for r in runs if r.results and (m == "sft" or r.method == m)), None)
        if run is None:
            continue
        policy = "sft" if m == "sft" else "ppo"
        for split in ("ind", "ood"):  # the first task's episode (older evaluate artifacts: their one GIF per split)
            src = run.eval_dir / f"rollout_{policy}_{split}_{run.tasks[0]}.gif" if run.tasks else None
            if src is None or not src.is_file():
                src = run.eval_dir / f"rollout_{policy}_{split}.gif"
            name = _copy(src, out, f"rollout_{m}_{split}.gif")
            if name:
                gifs.append((name, f"{LABELS[m]}, {split.upper()} ({run.label})"))
    if gifs:
        rollout_strips([(cap, out / n) for n, cap in gifs], out / "rollouts.png")
        gifs.insert(0, ("rollouts.png", "Every GIF below as 8 evenly spaced GIF frames (third view; the GIF "
                                          "encoder merges identical consecutive frames)"))
        md = "\n\n".join(f"{cap}\n\n![{n}]({n})" for n, cap in gifs)
        hb = "".join(f"<figure><img src='{n}'><figcaption>{cap}</figcaption></figure>" for n, cap in gifs)
        sections.append(("Rollouts in the simulator, one IND and one OOD episode per method (Figs. 4-5)", md, hb))
    ev = next((r for r in runs if r.eval_dir is not None), None)
    if ev is not None and _copy(ev.eval_dir / "extreme_actions.png", out, "extreme_actions.png"):
        sections.append(("The action world model under extreme actions (Fig. 9)", *image_section(["extreme_actions.png"])))
    return sections


def _diagnostics_section(runs: list[PointRun]) -> tuple[str, str, str] | None:
    diag: dict[str, list[float]] = {}
    for run in runs:
        for k, v in run.rl_metrics.items():
            if k.startswith("diagnostics/") and k.endswith("spearman_progress"):
                diag.setdefault(k, []).append(np.nan if v is None else float(v))  # null: constant reward
    if not diag:
        return None
    body = []
    for k, v in sorted(diag.items()):
        v = np.asarray(v)
        ok = v[~np.isnan(v)]
        body.append([k.removeprefix("diagnostics/"), f"{len(ok)} of {len(v)}",
                     f"{ok.mean():.3f}" if len(ok) else "undefined (constant reward)",
                     f"{ok.std(ddof=1):.3f}" if len(ok) > 1 else "-"])
    return _section("Reward diagnostics: Spearman correlation of reward with progress on held-out successful episodes",
                    "", ["metric", "runs", "mean", "sd"], body)


def report(points: list[dict], out: Path) -> Path:
    """Write ``report.md`` / ``report.html`` and their figures into ``out`` (the sweep's results directory)."""
    runs = [r for r in (gather(p) for p in points) if r is not None]
    sections = []
    if runs:
        sections += _success_sections(runs)
        sections += [s for s in (_paired_section(runs), _paired_by_task_section(runs)) if s]
        sections += [s for s in (_per_run_section(runs), _cost_section(runs), _diagnostics_section(runs)) if s]
        sections += _figure_sections(runs, out)
    write_report(out, "RoboScape-R sweep report",
                 sections or [("No results", "No point has a committed rl artifact yet.", None)])
    return out / "report.md"
