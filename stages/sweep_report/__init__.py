"""The sweep report: every point's evaluation pooled per method (seeds aggregated), plus the reward
diagnostics of every module. Hooked into ``pipeline.yaml`` as ``sweeps.<name>.report``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages.evaluate.report import (html_table, markdown_table, success_table, tally, write_report)
from stages.evaluate.writeup import METHODS

ORDER = ["sft", "rule", "wm", "embedding", "proxy"]


def _read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []


def report(points: list[dict], out: Path) -> Path:
    """Write ``report.md`` / ``report.html`` into ``out`` (the sweep's results directory)."""
    episodes, per_seed, diag, tasks = [], {}, {}, []
    for p in points:
        arts = p["artifacts"]
        rl = json.loads((arts["rl"] / "metrics.json").read_text()) if "rl" in arts else {}
        reward = rl.get("reward", p["values"].get("rl.reward", "?"))
        tasks = tasks or list(rl.get("tasks", []))
        for k, v in rl.items():
            if k.startswith("diagnostics/") and k.endswith("spearman_progress"):
                diag.setdefault(k, []).append(np.nan if v is None else float(v))  # null: undefined (constant reward)
        if "evaluate" not in arts:
            continue
        for r in _read_jsonl(arts["evaluate"] / "results.jsonl"):
            if "@" in r["policy"]:
                continue
            method = "sft" if r["policy"] == "sft" else reward
            episodes.append({**r, "policy": method})
            seed_key = (method, p["label"])
            per_seed.setdefault(seed_key, []).append(r)
    sections = []
    if episodes:
        counts = tally(episodes)
        methods = [m for m in ORDER if any(k[0] == m for k in counts)]
        rows = [("Supervised finetune (SFT), pooled over all points" if m == "sft" else METHODS[m], m) for m in methods]
        splits = [s for s in ("ind", "ood", "extra") if any(k[2] == s for k in counts)]
        header, body = success_table(counts, rows, tasks, splits)
        note = (f"{len(points)} sweep points; episodes pooled over seeds; success rate [95% Wilson] (successes/episodes).")
        sections.append(("Success in the simulator, seeds pooled (Table 1 layout)", note + "\n\n" + markdown_table(header, body),
                         f"<p>{note}</p>" + html_table(header, body)))
        seed_rows = []
        for m in methods:
            for split in splits:
                rates = [np.mean([r["success"] for r in rs if r["split"] == split])
                         for (mm, _), rs in per_seed.items() if mm == m and any(r["split"] == split for r in rs)]
                if rates:
                    seed_rows.append([METHODS.get(m, "SFT"), split, str(len(rates)), f"{np.mean(rates):.3f}",
                                      f"{np.std(rates, ddof=1):.3f}" if len(rates) > 1 else "-"])
        head = ["method", "split", "runs", "mean success", "sd over runs"]
        sections.append(("Per-run success (all tasks), mean and sd over runs", markdown_table(head, seed_rows),
                         html_table(head, seed_rows)))
    if diag:
        head = ["metric", "runs", "mean", "sd"]
        body = []
        for k, v in sorted(diag.items()):
            v = np.asarray(v)
            ok = v[~np.isnan(v)]
            body.append([k.removeprefix("diagnostics/"), f"{len(ok)} of {len(v)}",
                         f"{ok.mean():.3f}" if len(ok) else "undefined (constant reward)",
                         f"{ok.std(ddof=1):.3f}" if len(ok) > 1 else "-"])
        sections.append(("Reward diagnostics: Spearman correlation of reward with progress on held-out successful "
                         "episodes", markdown_table(head, body), html_table(head, body)))
    write_report(out, "RoboScape-R sweep report", sections or [("No results", "No point produced rl or evaluate metrics.", None)])
    return out / "report.md"
