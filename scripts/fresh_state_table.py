"""Every method against its SFT policy on the committed fresh-state episodes: one table, one figure.

The per-episode files under ``docs/results/fresh_states/`` (written by ``scripts/evaluate_sft.py
--out``: 100 fresh initial states per task and split, the same states for every policy of a seed)
are the evidence behind docs/RESULTS.md's headline numbers. ``comparisons.json`` beside them names,
for each method, its file stem, its seeds and the stem of the files it is paired with (usually the
seed's SFT policy). This script pairs them episode by episode (stages/sweep_report/paired.py), pools
the seeds, and gives both intervals: over the pooled episodes (these policies) and over the seeds
(Student-t: what another seed would give).

    PYTHONPATH=. .venv/bin/python scripts/fresh_state_table.py [--manifest M] [--figure PNG]
        [--by-task [--group push+pull=push,pull ...]] [--rates] [--rest] [--both-splits]

``--by-task`` adds a second table with the same two intervals per task (every task the episodes hold,
in the order they first appear) and per ``--group`` of tasks pooled (``NAME=task,task``; repeatable):
where in the task suite a method gains or loses. ``--rates`` adds the paper's Table 2 layout: each
compared policy's success rate per split and task, seeds pooled, and over all tasks with its 95%
Wilson interval (unpaired: the differences are in the tables above). ``--rest`` adds, per compared
policy and split, the share of its failed episodes that came to rest (the evaluate stage's
``rest_steps``, docs/evaluate.md) and of its successful ones; files written before episodes carried
``rest_steps`` give '-'. ``--both-splits`` adds, per comparison, the paired difference pooled over
its splits and seeds together (a prediction that pools IND and OOD, e.g. prediction 20 of docs/RESULTS.md).

File names: ``<stem>_s<seed>_<tag>_<date>.jsonl`` in domain, ``<stem>_ood_s<seed>_<tag>_<date>.jsonl``
out of domain; each (stem, seed, split) must match exactly one file. A comparison's ``tag`` is one
string, or a list of one tag per seed when its seeds ran on several builds of the store (each seed is
still paired within its own build).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages.sweep_report.paired import across_seeds, by_split, pair_up, paired_difference  # noqa: E402

FRESH = Path(__file__).resolve().parents[1] / "docs" / "results" / "fresh_states"
SPLITS = ("ind", "ood")
XLIM = 0.25  # the forest plot's half-width
LABEL_WIDTH = 70  # characters per line of a forest-plot label
FIELDS = {"label", "stem", "baseline", "seeds", "tag"}
OPTIONAL = {"splits"}  # default both; a method evaluated in one split only names it


@dataclass(frozen=True)
class Comparison:
    label: str      # the row's name
    stem: str       # file stem of the compared policy's episodes
    baseline: str   # file stem of the episodes it is paired with (e.g. "sft")
    seeds: tuple[int, ...]
    tag: str | tuple[str, ...]  # the machine/store tag in the file names (e.g. "epyc"), or one per seed
    splits: tuple[str, ...] = SPLITS

    def tag_of(self, seed: int) -> str:
        """The tag of ``seed``'s files (a sweep whose seeds ran on several builds of the store names one per seed)."""
        return self.tag if isinstance(self.tag, str) else self.tag[self.seeds.index(seed)]


def load_manifest(path: Path) -> list[Comparison]:
    """The manifest's comparisons; unknown or missing fields raise naming the entry."""
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"{path}: cannot read the manifest ({e})")
    if not isinstance(raw, dict) or set(raw) != {"comparisons"} or not isinstance(raw["comparisons"], list):
        raise SystemExit(f"{path}: expected {{\"comparisons\": [...]}}")
    out = []
    for i, entry in enumerate(raw["comparisons"]):
        if not isinstance(entry, dict) or not FIELDS <= set(entry) <= FIELDS | OPTIONAL:
            got = sorted(entry) if isinstance(entry, dict) else type(entry).__name__
            raise SystemExit(f"{path}: comparison {i} has fields {got}, expected {sorted(FIELDS)} "
                             f"and optionally {sorted(OPTIONAL)}")
        seeds = entry["seeds"]
        if not seeds or not all(isinstance(s, int) for s in seeds):
            raise SystemExit(f"{path}: comparison {i} ({entry['label']!r}): seeds must be a non-empty list of integers")
        splits = tuple(entry.get("splits", SPLITS))
        if not splits or not set(splits) <= set(SPLITS):
            raise SystemExit(f"{path}: comparison {i} ({entry['label']!r}): splits {list(splits)} not a subset of {list(SPLITS)}")
        tag = entry["tag"]
        if isinstance(tag, list):
            if len(tag) != len(seeds) or not all(isinstance(t, str) and t for t in tag):
                raise SystemExit(f"{path}: comparison {i} ({entry['label']!r}): tag is a list, so it needs one "
                                 f"non-empty tag per seed ({len(seeds)}), got {tag}")
            tag = tuple(tag)
        elif not isinstance(tag, str) or not tag:
            raise SystemExit(f"{path}: comparison {i} ({entry['label']!r}): tag must be a non-empty string or a list of one per seed")
        out.append(Comparison(entry["label"], entry["stem"], entry["baseline"], tuple(seeds), tag, splits))
    return out


def file_prefix(stem: str, seed: int, split: str, tag: str) -> str:
    """``<stem>_s<seed>_<tag>_`` in domain, ``<stem>_ood_s<seed>_<tag>_`` out of domain: a file's name before its date."""
    return f"{stem}_s{seed}_{tag}_" if split == "ind" else f"{stem}_ood_s{seed}_{tag}_"


def dated(folder: Path, prefix: str, suffix: str = ".jsonl") -> list[Path]:
    """The files ``<prefix><date><suffix>`` in ``folder`` (a date holds no '_', so a longer stem never matches)."""
    return sorted(p for p in folder.glob(f"{prefix}*{suffix}") if "_" not in p.name[len(prefix):-len(suffix)])


def episodes_file(folder: Path, stem: str, seed: int, split: str, tag: str) -> Path:
    """The one file holding ``stem``'s episodes of ``seed`` in ``split``."""
    name = file_prefix(stem, seed, split, tag)
    hits = dated(folder, name)
    if len(hits) != 1:
        raise SystemExit(f"{folder}: {len(hits)} files match {name}<date>.jsonl (expected one): {[p.name for p in hits]}")
    return hits[0]


def episodes(path: Path) -> list[dict]:
    """A results file's episodes; it must hold one policy's."""
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    policies = {r["policy"] for r in rows}
    if len(policies) != 1:
        raise SystemExit(f"{path}: expected one policy's episodes, found {sorted(policies)}")
    return rows


def compare(c: Comparison, folder: Path, tasks: frozenset[str] | None = None) -> dict[str, dict]:
    """Per split: the pooled paired difference, the per-seed differences and their across-seed interval;
    over the episodes of ``tasks`` only, when given."""
    out = {}
    for split in c.splits:
        pooled, per_seed = [], []
        for seed in c.seeds:
            method = episodes(episodes_file(folder, c.stem, seed, split, c.tag_of(seed)))
            base = episodes(episodes_file(folder, c.baseline, seed, split, c.tag_of(seed)))
            pairs = [(r, b) for r, b in pair_up(method, base)
                     if r["split"] == split and (tasks is None or r["task"] in tasks)]
            if not pairs:
                which = "" if tasks is None else f" (tasks {sorted(tasks)})"
                raise SystemExit(f"{c.label!r} seed {seed} {split}{which}: no episode shares an initial state with its baseline")
            pooled += pairs
            per_seed.append(by_split(pairs)[(split,)]["diff"])
        out[split] = {"pooled": by_split(pooled)[(split,)], "per_seed": per_seed, "seeds": across_seeds(per_seed)}
    return out


def both_splits(c: Comparison, folder: Path) -> dict:
    """The paired difference over every split and seed of ``c`` pooled (``paired_difference``'s dict)."""
    pairs = []
    for split in c.splits:
        for seed in c.seeds:
            method = episodes(episodes_file(folder, c.stem, seed, split, c.tag_of(seed)))
            base = episodes(episodes_file(folder, c.baseline, seed, split, c.tag_of(seed)))
            pairs += [(bool(r["success"]), b) for r, b in pair_up(method, base) if r["split"] == split]
    return paired_difference(pairs)


def both_table(rows: list[tuple[Comparison, dict]]) -> str:
    lines = ["| method | against | seeds | splits | pooled over splits and seeds | states better / worse | n |",
             "|---|---|---|---|---|---|---|"]
    for c, r in rows:
        lines.append(f"| {c.label} | `{c.baseline}` | {', '.join(map(str, c.seeds))} | {' + '.join(c.splits)} | "
                     f"{r['diff']:+.3f} [{r['lo']:+.3f}, {r['hi']:+.3f}] | {r['better']} / {r['worse']} | {r['n']:,} |")
    return "\n".join(lines)


def _cell(r: dict | None) -> str:
    """'pooled [interval] | across seeds [interval]' of one split's ``compare`` result."""
    if r is None:
        return "- | -"
    p, s = r["pooled"], r["seeds"]
    seeds = f"{s['diff']:+.2f} [{s['lo']:+.2f}, {s['hi']:+.2f}]" if s["k"] > 1 else "-"
    return f"{p['diff']:+.2f} [{p['lo']:+.2f}, {p['hi']:+.2f}] | {seeds}"


def table(rows: list[tuple[Comparison, dict]]) -> str:
    """A markdown table: pooled [interval] (n) and across seeds [interval] per split."""
    lines = ["| method | against | seeds | IND pooled | IND across seeds | OOD pooled | OOD across seeds | n per split |",
             "|---|---|---|---|---|---|---|---|"]
    for c, r in rows:
        seeds = ", ".join(map(str, c.seeds))
        n = r[c.splits[0]]["pooled"]["n"]
        lines.append(f"| {c.label} | `{c.baseline}` | {seeds} | {_cell(r.get('ind'))} | {_cell(r.get('ood'))} | {n:,} |")
    return "\n".join(lines)


def task_groups(comparisons: list[Comparison], folder: Path, groups: list[str]) -> list[tuple[str, frozenset[str]]]:
    """(name, tasks) per task the compared episodes hold (first-seen order), then per ``NAME=task,task`` group."""
    seen: dict[str, None] = {}
    for c in comparisons:
        for seed in c.seeds:
            for split in c.splits:
                for r in episodes(episodes_file(folder, c.stem, seed, split, c.tag_of(seed))):
                    seen.setdefault(r["task"], None)
    out = [(t, frozenset({t})) for t in seen]
    for g in groups:
        name, sep, members = g.partition("=")
        tasks = frozenset(t.strip() for t in members.split(",") if t.strip())
        if not sep or not name or not tasks:
            raise SystemExit(f"--group {g!r}: expected NAME=task,task (e.g. push+pull=push,pull)")
        unknown = sorted(tasks - set(seen))
        if unknown:
            raise SystemExit(f"--group {g!r}: tasks {unknown} are in no compared episode (tasks: {list(seen)})")
        out.append((name, tasks))
    return out


def task_table(rows: list[tuple[Comparison, str, dict]]) -> str:
    """The same table with a row per (comparison, task or task group)."""
    lines = ["| method | against | seeds | tasks | IND pooled | IND across seeds | OOD pooled | OOD across seeds | n per split |",
             "|---|---|---|---|---|---|---|---|---|"]
    for c, name, r in rows:
        n = r[c.splits[0]]["pooled"]["n"]
        lines.append(f"| {c.label} | `{c.baseline}` | {', '.join(map(str, c.seeds))} | {name} | "
                     f"{_cell(r.get('ind'))} | {_cell(r.get('ood'))} | {n:,} |")
    return "\n".join(lines)


def _policy_episodes(comparisons: list[Comparison], folder: Path):
    """(stem, seeds, episodes of every seed and split) for each comparison's baseline and compared
    stem, once per (stem, seeds, splits), baselines first; a file's rows of another split (older
    files held both) are left out, as ``compare`` leaves them out."""
    seen = set()
    for c in comparisons:
        for stem in (c.baseline, c.stem):
            if (stem, c.seeds, c.splits) in seen:
                continue
            seen.add((stem, c.seeds, c.splits))
            yield stem, c.seeds, [r for seed in c.seeds for split in c.splits
                                  for r in episodes(episodes_file(folder, stem, seed, split, c.tag_of(seed)))
                                  if r["split"] == split]


def rates(comparisons: list[Comparison], folder: Path) -> list[tuple[str, tuple[int, ...], dict]]:
    """Table 2's layout: (stem, seeds, {(split, task or "all"): (successes, episodes)}) per policy."""
    out = []
    for stem, seeds, rows in _policy_episodes(comparisons, folder):
        counts: dict[tuple[str, str], list[int]] = {}
        for r in rows:
            for cell in ((r["split"], r["task"]), (r["split"], "all")):
                k = counts.setdefault(cell, [0, 0])
                k[0] += bool(r["success"])
                k[1] += 1
        out.append((stem, seeds, {cell: tuple(k) for cell, k in counts.items()}))
    return out


def rest_rates(comparisons: list[Comparison], folder: Path) -> list[tuple[str, tuple[int, ...], dict]]:
    """(stem, seeds, {(split, "failed" | "succeeded"): (episodes that came to rest, episodes)}) per
    policy, over the episodes that carry ``rest_steps`` (the evaluate stage's own tally)."""
    from stages.evaluate.writeup import came_to_rest

    return [(stem, seeds, {(split, outcome): k for (_, split, outcome), k in came_to_rest(rows).items()})
            for stem, seeds, rows in _policy_episodes(comparisons, folder)]


def rest_table(rows: list[tuple[str, tuple[int, ...], dict]]) -> str:
    """Markdown: per split, the failed and the successful episodes that came to rest (Wilson intervals)."""
    from stages.evaluate.stats import fmt_rate

    head = [f"{split.upper()} {o} that came to rest" for split in SPLITS for o in ("failed", "succeeded")]
    lines = ["| policy | seeds | " + " | ".join(head) + " |", "|---|---|" + "---|" * len(head)]
    for stem, seeds, cells in rows:
        vals = [fmt_rate(*cells[(split, o)]) if (split, o) in cells else "-" for split in SPLITS for o in ("failed", "succeeded")]
        lines.append(f"| `{stem}` | {', '.join(map(str, seeds))} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def rates_table(rows: list[tuple[str, tuple[int, ...], dict]]) -> str:
    """Markdown: success rate per split and task (seeds pooled), and per split over all tasks with its
    95% Wilson interval and episode count; a cell the episodes lack is '-'."""
    from stages.evaluate.stats import wilson

    tasks = list(dict.fromkeys(t for _, _, cells in rows for (_, t) in cells if t != "all"))
    head = [f"{split.upper()} {t}" for split in SPLITS for t in [*tasks, "all"]]
    lines = ["| policy | seeds | " + " | ".join(head) + " |", "|---|---|" + "---|" * len(head)]
    for stem, seeds, cells in rows:
        vals = []
        for split in SPLITS:
            for t in tasks:
                k = cells.get((split, t))
                vals.append("-" if k is None else f"{k[0] / k[1]:.2f}")
            k = cells.get((split, "all"))
            if k is None:
                vals.append("-")
            else:
                rate, lo, hi = wilson(*k)
                vals.append(f"**{rate:.2f}** [{lo:.2f}, {hi:.2f}] (n = {k[1]:,})")
        lines.append(f"| `{stem}` | {', '.join(map(str, seeds))} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def figure(rows: list[tuple[Comparison, dict]], path: Path) -> None:
    """A forest plot per split: pooled interval (thick), across-seed interval (thin), seeds (dots)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # long labels wrapped, each row as tall as its label, so that none is cut off at the left edge
    labels = [textwrap.fill(c.label + ("" if c.baseline == "sft" else f", minus {c.baseline}"), LABEL_WIDTH)
              for c, _ in rows]
    heights = [max(1.0, 0.45 * (lab.count("\n") + 1)) for lab in labels]
    ys = [sum(heights[i + 1:]) + heights[i] / 2 for i in range(len(rows))]  # the first row on top
    fig, axes = plt.subplots(1, 2, figsize=(15, 0.42 * sum(heights) + 1.6), sharey=True, layout="constrained")
    for ax, split in zip(axes, SPLITS):
        for y, (c, r) in zip(ys, rows):
            if split not in r:
                continue
            res = r[split]
            s = res["seeds"]
            if s["k"] > 1 and not math.isnan(s["lo"]):
                ax.plot([s["lo"], s["hi"]], [y, y], color="0.6", lw=1)
            p = res["pooled"]
            ax.plot([p["lo"], p["hi"]], [y, y], color="C0", lw=4, solid_capstyle="butt")
            ax.plot(res["per_seed"], [y] * len(res["per_seed"]), "o", color="C1", ms=3)
            ax.plot([p["diff"]], [y], "|", color="k", ms=10)
        ax.axvline(0, color="k", lw=0.8)
        ax.set_xlim(-XLIM, XLIM)  # two-seed Student-t intervals run off it rather than squash the rest
        ax.set_title({"ind": "in domain", "ood": "out of domain"}[split])
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(ys, labels, fontsize=7)
    axes[0].set_ylim(0, sum(heights))
    fig.suptitle("thick: 95% interval over pooled episodes; thin: over seeds (Student-t, may run off the axis); dots: seeds", fontsize=9)
    fig.supxlabel("success minus SFT's (or the named baseline's), paired on the same initial states", fontsize=9)
    fig.savefig(path, dpi=110)  # the constrained layout leaves room for every label and both titles
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--manifest", type=Path, default=FRESH / "comparisons.json")
    ap.add_argument("--figure", type=Path, help="write the forest plot here (PNG)")
    ap.add_argument("--by-task", action="store_true", help="also print every comparison per task")
    ap.add_argument("--group", action="append", default=[], metavar="NAME=TASK,TASK",
                    help="with --by-task: also pool these tasks as one row (repeatable)")
    ap.add_argument("--rates", action="store_true",
                    help="also print each compared policy's success rate per split and task (Table 2's layout)")
    ap.add_argument("--rest", action="store_true",
                    help="also print each compared policy's share of failed / successful episodes that came to rest")
    ap.add_argument("--both-splits", action="store_true",
                    help="also print each comparison pooled over its splits and seeds together")
    args = ap.parse_args()
    if args.group and not args.by_task:
        ap.error("--group needs --by-task")
    folder = args.manifest.parent
    comparisons = load_manifest(args.manifest)
    rows = [(c, compare(c, folder)) for c in comparisons]
    print(table(rows))
    if args.by_task:
        groups = task_groups(comparisons, folder, args.group)
        print()
        print(task_table([(c, name, compare(c, folder, tasks)) for c in comparisons for name, tasks in groups]))
    if args.rates:
        print()
        print(rates_table(rates(comparisons, folder)))
    if args.rest:
        print()
        print(rest_table(rest_rates(comparisons, folder)))
    if args.both_splits:
        print()
        print(both_table([(c, both_splits(c, folder)) for c in comparisons]))
    if args.figure:
        figure(rows, args.figure)
        print(f"figure: {args.figure}", file=sys.stderr)


if __name__ == "__main__":
    main()
