"""Paired success differences: a fine-tuned policy vs the SFT policy it started from, episode by
episode on the same initial states (evaluate gives every policy the same task, scene and seed).

A pair is (success of the method, success of SFT) on one initial state; the difference is
+1, 0 or -1. Its mean is the change in success rate, with a 95% interval from the normal
approximation of the paired differences (their standard error is sqrt(var / n), the interval
clipped to [-1, 1]): pairing removes
the variance the two policies share (hard scenes fail for both), so it is far tighter than
comparing two Wilson intervals.

That interval treats the policies as fixed: it says how sure the states make us about *these*
policies. A method's claim ("PPO improves on SFT") is about what another seed would give, and the
seeds differ far more than the states' noise (on the `small` store, `rule` seeds 0 / 1 / 2 at -0.12 /
+0.02 / +0.06 IND, each within +-0.05): ``across_seeds`` gives the mean of the per-seed differences
with a Student-t interval over seeds, the honest interval with few seeds.
"""
from __future__ import annotations

import math
from collections import defaultdict

Z95 = 1.959964


def episode_id(r: dict) -> tuple:
    """What makes two evaluated episodes the same initial state."""
    return r["task"], r["split"], r.get("scene_id"), r["seed"]


def pair_up(method: list[dict], baseline: list[dict]) -> list[tuple[dict, bool]]:
    """(method episode, baseline success) for every method episode whose initial state the baseline also ran."""
    base = {episode_id(r): bool(r["success"]) for r in baseline}
    return [(r, base[episode_id(r)]) for r in method if episode_id(r) in base]


def paired_difference(pairs: list[tuple[bool, bool]]) -> dict:
    """Mean of success(method) - success(baseline) over ``pairs`` with its 95% interval.

    :return: {"diff", "lo", "hi", "n", "better", "worse"}: ``better`` / ``worse`` count the states
        only the method / only the baseline solved
    """
    n = len(pairs)
    d = [int(a) - int(b) for a, b in pairs]
    if n == 0:
        return {"diff": float("nan"), "lo": float("nan"), "hi": float("nan"), "n": 0, "better": 0, "worse": 0}
    mean = sum(d) / n
    var = sum((x - mean) ** 2 for x in d) / max(n - 1, 1)
    half = Z95 * math.sqrt(var / n)
    return {"diff": mean, "lo": max(mean - half, -1.0), "hi": min(mean + half, 1.0), "n": n,
            "better": sum(x > 0 for x in d), "worse": sum(x < 0 for x in d)}


def across_seeds(diffs: list[float]) -> dict:
    """Mean of per-seed paired differences with its 95% Student-t interval over the seeds (k - 1 degrees
    of freedom; NaN bounds with fewer than two seeds).

    :return: {"diff", "lo", "hi", "k", "sd"}
    """
    from scipy.stats import t

    k = len(diffs)
    if k == 0:
        return {"diff": float("nan"), "lo": float("nan"), "hi": float("nan"), "k": 0, "sd": float("nan")}
    mean = sum(diffs) / k
    if k < 2:
        return {"diff": mean, "lo": float("nan"), "hi": float("nan"), "k": 1, "sd": float("nan")}
    sd = math.sqrt(sum((x - mean) ** 2 for x in diffs) / (k - 1))
    half = float(t.ppf(0.975, k - 1)) * sd / math.sqrt(k)
    return {"diff": mean, "lo": max(mean - half, -1.0), "hi": min(mean + half, 1.0), "k": k, "sd": sd}


def fmt_across_seeds(res: dict) -> str:
    """'+0.03 [-0.09, +0.15] (3 seeds, sd 0.05)' for a table cell."""
    if res["k"] < 2:
        return "-"
    return f"{res['diff']:+.2f} [{res['lo']:+.2f}, {res['hi']:+.2f}] ({res['k']} seeds, sd {res['sd']:.2f})"


def by_split(paired: list[tuple[dict, bool]], keys=("split",)) -> dict[tuple, dict]:
    """``paired_difference`` per value of ``keys`` of the method's episodes (e.g. split, or task and split)."""
    groups: dict[tuple, list[tuple[bool, bool]]] = defaultdict(list)
    for r, base in paired:
        groups[tuple(r[k] for k in keys)].append((bool(r["success"]), base))
    return {k: paired_difference(v) for k, v in sorted(groups.items())}


def fmt_difference(res: dict) -> str:
    """'+0.12 [+0.03, +0.21] (n=200, 30 better / 6 worse)' for a table cell."""
    if not res["n"]:
        return "-"
    return (f"{res['diff']:+.2f} [{res['lo']:+.2f}, {res['hi']:+.2f}] "
            f"(n={res['n']}, {res['better']} better / {res['worse']} worse)")
