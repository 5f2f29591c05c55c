"""Success rates with 95% Wilson score intervals."""
from __future__ import annotations

import math


def wilson(successes: int, n: int, z: float = 1.959964) -> tuple[float, float, float]:
    """(rate, low, high) of ``successes`` out of ``n`` with the Wilson score interval (z = 1.96: 95%).

    Unlike the normal approximation it stays inside [0, 1] and is informative at 0/n and n/n.
    """
    if n <= 0:
        return float("nan"), 0.0, 1.0
    if not 0 <= successes <= n:
        raise ValueError(f"successes must lie in [0, {n}], got {successes}")
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return p, min(p, max(0.0, centre - half)), max(p, min(1.0, centre + half))  # p inside despite rounding


def fmt_rate(successes: int, n: int) -> str:
    """'0.40 [0.17, 0.69] (4/10)' for a table cell."""
    if n == 0:
        return "-"
    p, lo, hi = wilson(successes, n)
    return f"{p:.2f} [{lo:.2f}, {hi:.2f}] ({successes}/{n})"
