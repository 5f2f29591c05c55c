"""The evaluation report: the paper's table layouts, figures and GIFs, as report.md and report.html."""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from stages.collect.tasks import TITLES
from stages.evaluate.stats import fmt_rate, wilson

SPLITS = ("ind", "ood", "extra")
SPLIT_NAMES = {"ind": "IND", "ood": "OOD", "extra": "extra"}


def tally(results: list[dict]) -> dict[tuple[str, str, str], tuple[int, int]]:
    """(policy, task, split) -> (successes, episodes); task "all" pools the tasks."""
    out: dict[tuple[str, str, str], list[int]] = {}
    for r in results:
        for task in (r["task"], "all"):
            k = out.setdefault((r["policy"], task, r["split"]), [0, 0])
            k[0] += int(r["success"])
            k[1] += 1
    return {k: (v[0], v[1]) for k, v in out.items()}


def success_table(counts: dict, rows: list[tuple[str, str]], tasks: list[str], splits: list[str]) -> tuple[list[str], list[list[str]]]:
    """Header and cells: rows (label, policy key) x columns split x task (+ all tasks pooled)."""
    cols = [(s, t) for s in splits for t in [*tasks, "all"]]
    header = ["method"] + [f"{SPLIT_NAMES[s]} {TITLES.get(t, 'all tasks')}" for s, t in cols]
    body = [[label] + [fmt_rate(*counts.get((key, t, s), (0, 0))) for s, t in cols] for label, key in rows]
    return header, body


def markdown_table(header: list[str], body: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in body]
    return "\n".join(lines) + "\n"


def html_table(header: list[str], body: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    rows = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in body)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>"


def plot_success_vs_time(points: dict[str, list[tuple[float, int, int]]], path: Path, title: str) -> None:
    """points[split] = [(wall seconds, successes, n)] -> success rate with Wilson bars over wall time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    for split, pts in points.items():
        if not pts:
            continue
        pts = sorted(pts)
        x = [p[0] for p in pts]
        w = [wilson(k, n) for _, k, n in pts]
        y = [v[0] for v in w]
        ax.errorbar(x, y, yerr=[[v[0] - v[1] for v in w], [v[2] - v[0] for v in w]], marker="o", capsize=3,
                    label=SPLIT_NAMES.get(split, split))
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("training wall time (s)")
    ax.set_ylabel("success rate (95% Wilson)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_gif(frames: np.ndarray, path: Path, fps: int = 8) -> None:
    """(T, H, W, 3) uint8 -> an animated GIF (upscaled 2x so it is visible)."""
    from PIL import Image

    imgs = [Image.fromarray(f).resize((f.shape[1] * 2, f.shape[0] * 2), Image.NEAREST) for f in frames]
    imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=int(1000 / fps), loop=0)


def strip_figure(rows: list[tuple[str, np.ndarray]], path: Path, title: str) -> None:
    """rows of (label, (T, H, W, 3) uint8) -> one image, a labelled strip per row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = max(len(r[1]) for r in rows)
    h, w = rows[0][1].shape[1:3]
    cell, gap = 1.0, 0.16  # inches: a frame's width; the label line above each row
    n = len(rows)
    fig_w, fig_h = cell * t, n * (cell * h / w + gap) + 0.35  # frames touch side by side; 0.35 for the title
    fig, axes = plt.subplots(n, t, figsize=(fig_w, fig_h), squeeze=False,
                             gridspec_kw={"wspace": 0.02, "hspace": gap / (cell * h / w)})
    for i, (label, frames) in enumerate(rows):
        for j in range(t):
            ax = axes[i][j]
            ax.axis("off")
            if j < len(frames):
                ax.imshow(frames[j])
        axes[i][0].set_title(label, fontsize=7, loc="left")
    fig.suptitle(title, fontsize=9, y=1 - 0.08 / fig_h)
    fig.subplots_adjust(left=0.005, right=0.995, bottom=0.005, top=1 - (0.35 + gap) / fig_h)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_report(out: Path, title: str, sections: list[tuple[str, str, str | None]]) -> None:
    """sections: (heading, markdown body, html body or None to escape the markdown) -> report.md / .html."""
    md = [f"# {title}\n"]
    hb = [f"<!doctype html><meta charset='utf-8'><title>{html.escape(title)}</title>"
          "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse;font-size:12px}"
          "td,th{border:1px solid #ccc;padding:3px 6px}img{max-width:100%}</style>", f"<h1>{html.escape(title)}</h1>"]
    for heading, body_md, body_html in sections:
        md.append(f"## {heading}\n\n{body_md}\n")
        hb.append(f"<h2>{html.escape(heading)}</h2>" + (body_html if body_html is not None else f"<pre>{html.escape(body_md)}</pre>"))
    (out / "report.md").write_text("\n".join(md))
    (out / "report.html").write_text("\n".join(hb) + "\n")


def image_section(files: list[str]) -> tuple[str, str]:
    return ("\n".join(f"![{f}]({f})" for f in files), "".join(f"<p><img src='{html.escape(f)}'></p>" for f in files))
