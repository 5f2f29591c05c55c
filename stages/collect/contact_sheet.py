"""Render a contact sheet of a collect artifact: one strip per task (third view over wrist view).

    python -m stages.collect.contact_sheet <collect_artifact_dir> <out.png> [--frames 8] [--scale 2]

Each strip shows evenly spaced frames of the task's first successful optimal episode (any
episode if none succeeded), labelled with its instruction.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from stages.collect.dataset import Dataset
from stages.collect.tasks import TASKS

LABEL_H = 14


def _pick(ds: Dataset, task: str):
    eps = [m for m in ds.episodes if m.task == task]
    best = [m for m in eps if m.kind == "optimal" and m.success]
    return (best or eps or [None])[0]


def render(root: Path, n_frames: int = 8, scale: int = 2) -> Image.Image:
    """The contact sheet as an RGB image."""
    ds = Dataset(root)
    strips = []
    for task in TASKS:
        meta = _pick(ds, task)
        if meta is None:
            continue
        ep = ds.load(meta.episode_id)
        idx = np.linspace(0, len(ep.third) - 1, n_frames).round().astype(int)
        rows = [np.concatenate([getattr(ep, v)[i] for i in idx], axis=1) for v in ("third", "wrist")]
        strip = Image.fromarray(np.concatenate(rows, axis=0))
        strip = strip.resize((strip.width * scale, strip.height * scale), Image.NEAREST)
        labelled = Image.new("RGB", (strip.width, strip.height + LABEL_H), "white")
        ImageDraw.Draw(labelled).text((3, 1), f"{task}: {meta.instruction} ({meta.length} steps; top third view, bottom wrist)", fill="black")
        labelled.paste(strip, (0, LABEL_H))
        strips.append(labelled)
    if not strips:
        raise ValueError(f"{root} has no episodes")
    sheet = Image.new("RGB", (max(s.width for s in strips), sum(s.height + 4 for s in strips)), "white")
    y = 0
    for s in strips:
        sheet.paste(s, (0, y))
        y += s.height + 4
    return sheet


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("artifact", type=Path, help="collect artifact directory")
    ap.add_argument("out", type=Path, help="output PNG path")
    ap.add_argument("--frames", type=int, default=8, help="frames per strip")
    ap.add_argument("--scale", type=int, default=2, help="integer upscaling of the 64x64 frames")
    args = ap.parse_args(argv)
    render(args.artifact, args.frames, args.scale).save(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
