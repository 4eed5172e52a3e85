"""Clustering metrics over (policy id, true group id) pairs, one pair per training episode.

* the Adjusted Rand Index (scikit-learn's ``adjusted_rand_score``): 1.0 when policies and groups
  are the same partition of the episodes (up to renaming), about 0 for a random assignment;
* per-policy episode counts;
* the confusion table policy x group (how many episodes of each group each policy served).
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Sequence

import numpy as np

__all__ = ["adjusted_rand_index", "policy_counts", "confusion_table"]


def _pairs(policy_ids: Sequence[int], group_ids: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(policy_ids, dtype=np.int64).reshape(-1)
    g = np.asarray(group_ids, dtype=np.int64).reshape(-1)
    if p.shape != g.shape:
        raise ValueError(f"policy_ids has {p.size} entries but group_ids has {g.size}")
    return p, g


def adjusted_rand_index(policy_ids: Sequence[int], group_ids: Sequence[int]) -> float | None:
    """ARI between the two labelings (None when there are no episodes yet)."""
    from sklearn.metrics import adjusted_rand_score

    p, g = _pairs(policy_ids, group_ids)
    if p.size == 0:
        return None
    return float(adjusted_rand_score(g, p))


def policy_counts(policy_ids: Sequence[int]) -> dict[int, int]:
    """Episodes per policy id, sorted by id."""
    counts = Counter(int(p) for p in policy_ids)
    return {k: counts[k] for k in sorted(counts)}


def confusion_table(policy_ids: Sequence[int], group_ids: Sequence[int]) -> dict[str, Any]:
    """``{"policies": [...], "groups": [...], "counts": [[episodes of group g served by policy p]]}``.

    Rows follow ``policies`` and columns follow ``groups`` (both sorted ids); JSON-safe.
    """
    p, g = _pairs(policy_ids, group_ids)
    policies = sorted(set(p.tolist()))
    groups = sorted(set(g.tolist()))
    row = {pid: i for i, pid in enumerate(policies)}
    col = {gid: j for j, gid in enumerate(groups)}
    counts = np.zeros((len(policies), len(groups)), dtype=np.int64)
    for pi, gi in zip(p.tolist(), g.tolist()):
        counts[row[pi], col[gi]] += 1
    return {"policies": policies, "groups": groups, "counts": counts.tolist()}
