"""Success rates and their Wilson intervals on known inputs."""
import pytest

from stages.evaluate.report import tally
from stages.evaluate.stats import fmt_rate, wilson


@pytest.mark.parametrize("k,n,expected", [
    (0, 10, (0.0, 0.0, 0.2775)),       # published Wilson 95% values
    (5, 10, (0.5, 0.2366, 0.7634)),
    (10, 10, (1.0, 0.7225, 1.0)),
    (1, 20, (0.05, 0.0089, 0.2361)),
    (81, 263, (0.3080, 0.2553, 0.3662)),
])
def test_wilson_known_values(k, n, expected):
    assert wilson(k, n) == pytest.approx(expected, abs=1e-4)


def test_wilson_edges_and_errors():
    p, lo, hi = wilson(0, 0)
    assert p != p and (lo, hi) == (0.0, 1.0)  # no episodes: NaN rate, the whole interval
    with pytest.raises(ValueError):
        wilson(11, 10)
    assert fmt_rate(4, 10) == "0.40 [0.17, 0.69] (4/10)"
    assert fmt_rate(0, 0) == "-"


def test_tally_pools_tasks():
    rs = [{"policy": "ppo", "task": t, "split": "ind", "success": s} for t, s in
          [("push", True), ("push", False), ("pull", True)]]
    c = tally(rs)
    assert c[("ppo", "push", "ind")] == (1, 2) and c[("ppo", "all", "ind")] == (2, 3)


def test_wilson_interval_contains_the_rate_exactly():
    # at k = n the upper bound is 1 in exact arithmetic but rounded below the rate (0.9999999999999999
    # at 4/4 and 10/10), which made error bars negative and the success-vs-time plot raise
    for n in range(1, 201):
        for k in range(n + 1):
            p, lo, hi = wilson(k, n)
            assert lo <= p <= hi, (k, n, lo, p, hi)
