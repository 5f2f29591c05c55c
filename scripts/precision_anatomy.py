"""Where the false imagined successes are: the rl stage's ``imagined.json`` taken apart.

Imagined-success precision (the rl stage's ``imagined/<split>/precision``) is one number per split:
of the final policy's imagined episodes the done head ended as a success, the share whose actions,
replayed open loop in ManiSkill from the same initial state, succeed by the step the head fired.
This script reads the per-environment rows behind it (``<rl>/imagined.json``, one or more rl
artifacts pooled) and splits it three ways:

- by the imagined step the head fired at (``done_at``): are early imagined successes real more
  often than late ones (the world model's picture fades with the horizon)?
- by task;
- the false ones by what their replay did: never succeeded within the horizon, or succeeded a
  few steps *after* the head fired (the head early, not wrong: a ``--slack`` of k steps counts
  those as real, a looser metric than the stage's).

``--theta`` / ``--persist`` recount the rows at another done threshold or hold (from the recorded
probabilities, as the stage's ``precision_at_*`` / ``precision_persist_*``); by default each row is
counted as the stage counted it.

    PYTHONPATH=. .venv/bin/python scripts/precision_anatomy.py <rl> [<rl> ...] [--theta 0.5] [--persist 1]
        [--bins 10 20 40] [--slack 3 10] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages.evaluate.stats import wilson  # noqa: E402
from stages.rl.imagined import Replay, replay_row  # noqa: E402

IMAGINED_FILE = "imagined.json"


def load_rows(rl: Path) -> dict[str, list[Replay]]:
    """{split: rows} of one rl artifact (or of an ``imagined.json`` given directly)."""
    path = rl if rl.suffix == ".json" else rl / IMAGINED_FILE
    if not path.is_file():
        raise SystemExit(f"{path}: no such file (an rl artifact written since the imagined-success check "
                         "keeps its rows; rl.precision_envs 0 writes none)")
    try:
        table = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SystemExit(f"{path}: not JSON ({e})") from None
    fields = set(Replay.__dataclass_fields__)
    out = {}
    for split, rows in table.items():
        bad = [sorted(set(r) - fields) for r in rows if not set(r) <= fields]
        if bad:
            raise SystemExit(f"{path}: split {split!r} has rows with unknown fields {bad[0]}")
        out[split] = [Replay(**{k: tuple(v) if isinstance(v, list) else v for k, v in r.items()}) for r in rows]
    return out


def recount(rows: list[Replay], theta: float | None, persist: int | None) -> list[Replay]:
    """The rows as a done threshold ``theta`` held for ``persist`` steps would have counted them
    (None, None: unchanged)."""
    if theta is None and persist is None:
        return rows
    if theta is None:
        raise SystemExit("--persist needs --theta (the threshold the stage ran with is not in imagined.json)")
    return [replay_row(r.env_id, np.asarray(r.done_probs), r.first_success, theta, r.tcp_error, persist or 1)
            for r in rows]


def task_of(row: Replay) -> str:
    return row.env_id.split("/", 1)[0]


def bin_of(step: int, edges: tuple[int, ...]) -> str:
    """``1-10``, ``11-20``, ..., ``41+`` for ``edges`` (10, 20, 40)."""
    lo = 1
    for e in edges:
        if step <= e:
            return f"{lo}-{e}"
        lo = e + 1
    return f"{lo}+"


def fate(row: Replay, slacks: tuple[int, ...]) -> str:
    """What the replay of an imagined success did: ``real`` (succeeded by the head's step), ``later by
    <= k`` (the first success within the smallest slack k after it), ``later`` (beyond every slack), or
    ``never`` within the horizon."""
    if row.success:
        return "real"
    if row.first_success <= 0:
        return "never"
    late = row.first_success - row.done_at
    for k in sorted(slacks):
        if late <= k:
            return f"later by <= {k}"
    return "later"


def anatomy(rows: list[Replay], edges: tuple[int, ...], slacks: tuple[int, ...]) -> dict:
    """Counts of one split's imagined successes: overall, by done step bin, by task, by fate, and the
    precision a slack of k steps would give."""
    done = [r for r in rows if r.done_at > 0]

    def rate(k: int, n: int) -> dict:
        p, lo, hi = wilson(k, n) if n else (None, None, None)
        return {"real": k, "imagined": n, "precision": p, "lo": lo, "hi": hi}

    groups = {"by_step": defaultdict(list), "by_task": defaultdict(list)}
    for r in done:
        groups["by_step"][bin_of(r.done_at, edges)].append(r)
        groups["by_task"][task_of(r)].append(r)
    order = [bin_of(e, edges) for e in edges] + [bin_of(edges[-1] + 1, edges)] if edges else []
    out = {"environments": len(rows), "all": rate(sum(r.success for r in done), len(done)),
           "by_step": {b: rate(sum(r.success for r in groups["by_step"][b]), len(groups["by_step"][b]))
                       for b in order if groups["by_step"][b]},
           "by_task": {t: rate(sum(r.success for r in v), len(v)) for t, v in sorted(groups["by_task"].items())},
           "fate": {}, "slack": {}}
    for r in done:
        f = fate(r, slacks)
        out["fate"][f] = out["fate"].get(f, 0) + 1
    for k in slacks:
        real = sum(r.success or (r.first_success > 0 and r.first_success - r.done_at <= k) for r in done)
        out["slack"][k] = rate(real, len(done))
    return out


def fmt(r: dict) -> str:
    if not r["imagined"]:
        return "0 imagined"
    return f"{r['real']}/{r['imagined']} = {r['precision']:.2f} [{r['lo']:.2f}, {r['hi']:.2f}]"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rl", type=Path, nargs="+", help="rl artifact folders (or imagined.json files), pooled")
    ap.add_argument("--theta", type=float, default=None, help="recount at this done threshold")
    ap.add_argument("--persist", type=int, default=None, help="recount with the head held this many steps (needs --theta)")
    ap.add_argument("--bins", type=int, nargs="+", default=[10, 20, 40], help="upper edges of the done-step bins")
    ap.add_argument("--slack", type=int, nargs="+", default=[3, 10], help="steps after the head's a replay may succeed")
    ap.add_argument("--json", type=Path, default=None, help="also write the counts here")
    args = ap.parse_args()
    if sorted(set(args.bins)) != args.bins or args.bins[0] < 1:
        ap.error(f"--bins must be increasing positive steps, got {args.bins}")
    if any(k < 1 for k in args.slack):
        ap.error(f"--slack must be positive steps, got {args.slack}")
    if args.persist is not None and args.persist < 1:
        ap.error(f"--persist must be >= 1, got {args.persist}")
    pooled: dict[str, list[Replay]] = defaultdict(list)
    for rl in args.rl:
        for split, rows in load_rows(rl).items():
            pooled[split] += recount(rows, args.theta, args.persist)
    report = {}
    for split in sorted(pooled):
        a = report[split] = anatomy(pooled[split], tuple(args.bins), tuple(args.slack))
        print(f"{split}: {a['environments']} environments, imagined successes real {fmt(a['all'])}")
        print("  by the imagined step the head fired at: " + "; ".join(f"{b}: {fmt(r)}" for b, r in a["by_step"].items()))
        print("  by task: " + "; ".join(f"{t}: {fmt(r)}" for t, r in a["by_task"].items()))
        print("  replays of the imagined successes: " + ", ".join(f"{k} {v}" for k, v in sorted(a["fate"].items())))
        print("  precision with slack: " + "; ".join(f"{k} steps {fmt(r)}" for k, r in a["slack"].items()))
    if args.json is not None:
        args.json.write_text(json.dumps({"rl": [str(p) for p in args.rl], "theta": args.theta, "persist": args.persist,
                                         "splits": report}, indent=1) + "\n")


if __name__ == "__main__":
    main()
