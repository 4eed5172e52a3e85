"""Clustering metrics over (policy id, true group id) pairs, one pair per training episode.

* the Adjusted Rand Index (Hubert and Arabie, 1985): 1.0 when policies and groups are the same
  partition of the episodes (up to renaming), about 0 for a random assignment. Computed here from
  the contingency table rather than with scikit-learn's ``adjusted_rand_score``, whose import costs
  a clustering process ~1.5 s of its start on 2 cores; the tests check both agree;
* per-policy episode counts;
* the confusion table policy x group (how many episodes of each group each policy served);
* the calibrated rule's tail (:func:`calibration_tail`): how often a batch's own policy saw no null
  draw reach the observed distance in its first ``k - 1`` draws, against the ``1 / k`` of frames
  that are exchangeable with the buffer's (the rule's false-split rate is exact only then).
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Sequence

import numpy as np

from .calibration import accepts

__all__ = ["adjusted_rand_index", "calibration_tail", "confusion_table", "policy_counts", "table_metrics"]


def _pairs(policy_ids: Sequence[int], group_ids: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(policy_ids, dtype=np.int64).reshape(-1)
    g = np.asarray(group_ids, dtype=np.int64).reshape(-1)
    if p.shape != g.shape:
        raise ValueError(f"policy_ids has {p.size} entries but group_ids has {g.size}")
    return p, g


def adjusted_rand_index(policy_ids: Sequence[int], group_ids: Sequence[int]) -> float | None:
    """ARI between the two labelings (None when there are no episodes yet).

    With ``pairs(x) = x (x - 1) / 2`` summed over the cells (``index``), the row sums (``a``) and the
    column sums (``b``) of the policy x group contingency table of ``n`` episodes:
    ``(index - a b / pairs(n)) / ((a + b) / 2 - a b / pairs(n))``; 1.0 when the denominator is 0
    (both labelings put every episode alone, or all in one cluster: the same partition). Python
    integers: no overflow for any number of episodes."""
    p, g = _pairs(policy_ids, group_ids)
    if p.size == 0:
        return None
    _, p_codes = np.unique(p, return_inverse=True)
    _, g_codes = np.unique(g, return_inverse=True)
    table = np.zeros((int(p_codes.max()) + 1, int(g_codes.max()) + 1), dtype=np.int64)
    np.add.at(table, (p_codes, g_codes), 1)
    return _ari(table)


def _ari(table: np.ndarray) -> float:
    """ARI of a policy x group contingency table (see :func:`adjusted_rand_index`)."""

    def pairs(counts: np.ndarray) -> int:
        return sum(int(c) * (int(c) - 1) // 2 for c in counts.ravel())

    n = int(table.sum())
    index, a, b, total = pairs(table), pairs(table.sum(axis=1)), pairs(table.sum(axis=0)), n * (n - 1) // 2
    if total == 0:
        return 1.0
    expected = a * b / total
    denominator = (a + b) / 2 - expected
    if denominator == 0:
        return 1.0
    return float((index - expected) / denominator)


def table_metrics(counts: dict[tuple[int, int], int]) -> dict[str, Any]:
    """ARI, episodes, per-policy counts and the confusion table from ``{(policy, group): episodes}``
    (what :class:`~covers_dist.clustering.bank.PolicyBank` keeps as episodes are labelled): the same
    figures as :func:`adjusted_rand_index`, :func:`policy_counts` and :func:`confusion_table` over the
    episodes, in time that does not grow with their number."""
    cells = {k: int(v) for k, v in counts.items() if v}
    policies = sorted({p for p, _ in cells})
    groups = sorted({g for _, g in cells})
    row = {pid: i for i, pid in enumerate(policies)}
    col = {gid: j for j, gid in enumerate(groups)}
    table = np.zeros((len(policies), len(groups)), dtype=np.int64)
    for (p, g), c in cells.items():
        table[row[p], col[g]] = c
    return {
        "ari": _ari(table) if cells else None,
        "episodes_labelled": int(table.sum()),
        "policy_counts": {str(p): int(table[row[p]].sum()) for p in policies},
        "confusion": {"policies": policies, "groups": groups, "counts": table.tolist()},
    }


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


def _majority(groups: Sequence[int] | None) -> int | None:
    if not groups:
        return None
    return Counter(int(g) for g in groups).most_common(1)[0][0]


def _first_exceedance(test: dict[str, Any], draws: int, rate: float) -> int | None:
    """Index of a test's first null draw at or above the observed distance, ``draws + 1`` when
    none of its ``draws`` reached it, None when the record does not say (the test went on past
    its first exceedance, so where that came is unknown)."""
    if not test.get("tested") or test.get("exceedances") is None:
        return None
    made, count = int(test["draws"]), int(test["exceedances"])
    if count == 0:
        return made + 1 if made == draws else None
    # the test stops at the first exceedance that settles acceptance; with one exceedance
    # enough, that is the first exceedance
    if count == 1 and accepts(1, draws, rate):
        return made
    return None


def calibration_tail(records: Sequence[Any]) -> dict[str, Any] | None:
    """The calibrated rule's tail over a run's assignment records (None when no record was made by
    the calibrated rule).

    Each permutation test draws null splits until acceptance is settled (docs/guide/clustering.md). For
    the test of a batch's *own* policy, the event "no null draw reached the observed distance in
    the first ``k - 1`` draws" has probability ``1 / k`` when the batch's frames are exchangeable
    with the buffer's (the premise of the rule's exact false-split rate), and a rejection is that
    event at ``k = N + 1``. ``rows`` counts it for ``k`` = 10, 100, ... up to ``N + 1`` beside the
    ``tests / k`` expected; a count well above the expectation at large ``k`` says the frames are
    not exchangeable there and the run's false splits will exceed the configured rate.

    Which test is the batch's own: a recall's test of the recalled policy, and with true group ids
    (``true_groups``, metrics only) a ``new`` decision for a group that already had a policy (a
    false split): its nearest policy's test. Without group ids ``new`` decisions are left out
    (``labelled: False``), as are recalls of a group's first batch into another group's policy,
    decisions at the cap, and tests the threshold decided or whose first exceedance the record
    does not give (``skipped``)."""
    recs = [r for r in records if getattr(r, "calibration", None)]
    if not recs:
        return None
    draws = max(int(r.calibration.get("max_draws", 0)) for r in recs)
    rate = float(recs[-1].calibration.get("false_split_rate", 0.0))
    seen: set[int] = set()
    labelled = all(r.true_groups for r in records)
    firsts: list[int] = []
    skipped = false_splits = 0
    for r in records:
        group = _majority(r.true_groups)
        first_of_group = group is not None and group not in seen
        if group is not None:
            seen.add(group)
        cal = getattr(r, "calibration", None)
        if not cal or r.decision in ("adopt", "recall_at_cap") or first_of_group:
            continue
        tests = cal.get("policies", {})
        if r.decision == "recall":
            test = tests.get(str(r.policy_id))
        elif r.decision == "new" and group is not None:
            false_splits += 1
            near = min(r.distances, key=lambda pid: (r.distances[pid], pid)) if r.distances else None
            test = tests.get(str(near))
        else:
            continue
        first = _first_exceedance(test or {}, int(cal.get("max_draws", draws)), rate)
        if first is None:
            skipped += 1
            continue
        firsts.append(first)
    n = len(firsts)
    ks = [10**j for j in range(1, 12) if 10**j <= draws + 1]
    if draws + 1 not in ks:
        ks.append(draws + 1)
    rows = [{"k": k, "count": sum(f >= k for f in firsts), "expected": n / k} for k in ks]
    return {
        "tests": n,
        "skipped": skipped,
        "max_draws": draws,
        "false_split_rate": rate,
        "false_splits": false_splits if labelled else None,
        "labelled": labelled,
        "rows": rows,
    }
