"""Success figures with their n: counts, the Wilson 95% interval.

Every success rate the project reports comes with the number of episodes behind it and a 95%
interval (Wilson's score interval, which stays inside [0, 1] and is not degenerate at 0 or 1,
unlike the normal approximation; Agarwal et al. 2021 on reporting RL evidence with its n).
Plain Python.
"""

from __future__ import annotations

import math
import statistics
from typing import Any, Sequence

__all__ = ["Z95", "NEAR_MISS", "wilson_interval", "success_summary", "miss_summary"]

#: The normal quantile of a two-sided 95% interval.
Z95 = 1.959963984540054

#: A failed episode whose closest approach was within this many success radii is a near miss.
NEAR_MISS = 1.5


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval for ``successes`` out of ``n`` Bernoulli trials (``n >= 1``)."""
    if n < 1:
        raise ValueError(f"need at least one trial, got n={n}")
    if not 0 <= successes <= n:
        raise ValueError(f"successes must be in [0, n={n}], got {successes}")
    p = successes / n
    z2 = z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def success_summary(outcomes: Sequence[float], state_keys: Sequence[Any] | None = None) -> dict[str, Any]:
    """``{"success", "n", "successes", "ci95", "distinct_initial_states"}`` of per-episode outcomes
    (an episode succeeded when its outcome is > 0; ``distinct_initial_states`` counts different
    keys, or None without keys)."""
    n = len(outcomes)
    if n < 1:
        raise ValueError("no episodes to summarise")
    k = sum(1 for s in outcomes if float(s) > 0.0)
    lo, hi = wilson_interval(k, n)
    keys = [key for key in (state_keys or []) if key is not None]
    return {
        "success": k / n,
        "n": n,
        "successes": k,
        "ci95": [round(lo, 4), round(hi, 4)],
        "distinct_initial_states": len(set(keys)) if keys else None,
    }


def miss_summary(outcomes: Sequence[float], closest: Sequence[float | None] | None) -> dict[str, Any]:
    """How far the failed episodes stayed from success, from each episode's ``closest`` approach in
    success radii (``info["target_ratio"]``): ``{"misses", "misses_closest_median", "near_misses"}``
    (failures with a closest approach, the median of those approaches, and how many were within
    :data:`NEAR_MISS` radii). ``{}`` when no failed episode has one (no failures, or an env that
    reports no ratio)."""
    pairs = list(zip(outcomes, closest or []))
    failed = [float(c) for s, c in pairs if float(s) <= 0.0 and c is not None]
    if not failed:
        return {}
    return {
        "misses": len(failed),
        "misses_closest_median": round(float(statistics.median(failed)), 4),
        "near_misses": sum(1 for c in failed if c <= NEAR_MISS),
    }
