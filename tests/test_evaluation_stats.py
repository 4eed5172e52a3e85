"""Success figures with their n: the Wilson interval against values known by hand, and the summary."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covers_dist.evaluation.stats import NEAR_MISS, miss_summary, success_summary, wilson_interval


def test_wilson_interval_matches_values_known_by_hand():
    # 0 of n: the upper end is z^2 / (n + z^2)
    z2 = 1.959963984540054**2
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(z2 / (10 + z2), abs=1e-12)
    lo, hi = wilson_interval(10, 10)
    assert hi == pytest.approx(1.0, abs=1e-12) and lo == pytest.approx(10 / (10 + z2), abs=1e-12)
    assert wilson_interval(5, 10) == pytest.approx((0.236593, 0.763407), abs=1e-6)
    assert wilson_interval(64, 128) == pytest.approx((0.414652, 0.585348), abs=1e-6)


def test_wilson_interval_covers_the_rate_at_about_95_percent():
    rng = np.random.default_rng(0)
    for p, n in ((0.1, 16), (0.5, 16), (0.9, 64)):
        ks = rng.binomial(n, p, size=4000)
        covered = np.mean([lo <= p <= hi for lo, hi in (wilson_interval(int(k), n) for k in ks)])
        assert 0.92 <= covered <= 0.99, (p, n, covered)


@pytest.mark.parametrize(("k", "n"), [(-1, 4), (5, 4), (0, 0)])
def test_wilson_interval_refuses_impossible_counts(k, n):
    with pytest.raises(ValueError):
        wilson_interval(k, n)


def test_success_summary_counts_episodes_and_distinct_states():
    s = success_summary([1.0, 0.0, 1.0, 1.0], ["a", "b", "a", "c"])
    assert (s["success"], s["n"], s["successes"], s["distinct_initial_states"]) == (0.75, 4, 3, 3)
    lo, hi = s["ci95"]
    assert lo < 0.75 < hi and math.isclose(lo, wilson_interval(3, 4)[0], abs_tol=1e-4)
    assert success_summary([0.0])["distinct_initial_states"] is None
    with pytest.raises(ValueError):
        success_summary([])


def test_miss_summary_says_how_far_the_failures_stayed():
    out = miss_summary([1.0, 0.0, 0.0, 0.0, 0.0], [0.4, 1.2, 3.0, 1.5, None])
    assert out == {"misses": 3, "misses_closest_median": 1.5, "near_misses": 2}  # 1.2 and 1.5 <= NEAR_MISS
    assert NEAR_MISS == 1.5
    assert miss_summary([1.0, 1.0], [0.2, 0.9]) == {}  # no failures
    assert miss_summary([0.0, 0.0], [None, None]) == {}  # an env that reports no ratio
    assert miss_summary([0.0, 0.0], None) == {}


def test_pairs_table_shows_the_misses_only_where_an_env_reported_them():
    from covers_dist.evaluation.report import pairs_table

    def pair(g, results):
        return {"task": "reach-v3", "g": g, "status": "seen", "agnostic_policy": 0, "agnostic_decision": "recall",
                "oracle_policy": 0, "results": {"greedy/agnostic": results}}  # fmt: skip

    plain = {"modes": ["greedy"], "selections": ["agnostic"], "pairs": [pair("e", {"success": 1.0, "successes": 4, "n": 4})]}
    assert "misses" not in pairs_table(plain)
    miss = {"success": 0.5, "successes": 2, "n": 4, "misses": 2, "misses_closest_median": 1.12, "near_misses": 2}
    table = pairs_table({**plain, "pairs": plain["pairs"] + [pair("r", miss)]})
    assert "misses greedy/agnostic" in table.splitlines()[0]
    assert "2 at 1.12 radii (2 near)" in table
    assert table.splitlines()[2].rstrip(" |").endswith("-")  # e: no failures
