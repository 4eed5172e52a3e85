"""The calibrated rule's test: an exact permutation test of "O and B_i are samples of one distribution".

For policy ``i`` with ``m = |O|`` and ``n = |B_i|`` the features of ``O`` and ``B_i`` are pooled
(``m + n`` vectors, from the one encoder pass that gives the observed distance). Each null draw
splits the pool uniformly at random into ``m`` and ``n`` vectors (without replacement: a random
permutation of the pool) and computes the same statistic, the bank's metric under its feature
normalization, between the two parts. Under the null every split of the pool is equally likely to
be the observed one, so the observed ``d(O, B_i)`` and the draws are exchangeable and
``p = (1 + #{null >= observed}) / (1 + draws)`` is an exact p-value (ties count against ``O``).

:func:`max_draws` gives the number of draws ``N`` of the test from the configured rate (enough that
``1 / (1 + N) <= rate``); :func:`permutation_test` runs it, stopping as soon as the decision can no
longer change (then the decision is that of the test with all ``N`` draws).

:class:`NullDistance` holds the pooled features and returns the distance between the two parts of
a permutation ``idx``: ``d(pool[idx[:m]], pool[idx[m:]])``, with the bank's metric and feature
normalization. For W1 and the mean Euclidean distance under the ``buffer``, ``none`` and ``l2``
normalizations it reuses the pool's pairwise distance matrix (computed once) instead of
recomputing ``pdist`` and ``cdist`` per draw: the result equals
``distance(*normalize_pair(O', B', norm))`` up to rounding (tested). Other cases (Mahalanobis, a
part whose spread is zero) take that generic path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .distances import get_distance
from .features import normalize_pair

__all__ = [
    "NullDistance",
    "PermutationResult",
    "accepts",
    "max_draws",
    "null_split",
    "permutation_test",
    "splits_suffice",
    "transport_cost",
]


def transport_cost(a: np.ndarray, b: np.ndarray, cost: np.ndarray, max_iter: int) -> float:
    """The optimal transport cost between weights ``a`` and ``b`` (``cost``: a C-ordered float64
    matrix), as ``ot.emd2`` returns it. Calls POT's network simplex core directly: ``ot.emd2``'s
    argument checks, backend dispatch and dual centering took about two thirds of a call on an
    8 x 128 problem, and a test makes up to ``N`` calls. Falls back to ``ot.emd2`` (and its
    warnings) when the core is unavailable or does not report an optimal solution."""
    from .._imports import import_lightly

    ot = import_lightly("ot")
    try:
        from ot.lp.emd_wrap import emd_c
    except ImportError:  # pragma: no cover - another POT layout
        emd_c = None
    if emd_c is not None:
        result = emd_c(a, b, cost, max_iter, 1)
        if result[4] == 1:  # OPTIMAL
            return float(result[1])
    return float(ot.emd2(a, b, cost, numItermax=max_iter))


class NullDistance:
    """``d(pool[idx[:m]], pool[idx[m:]])`` for index permutations ``idx`` of a set of features
    (the calibrated rule passes the pooled features of ``O`` and ``B_i``)."""

    def __init__(self, pool: np.ndarray, m: int, metric: str, norm: str) -> None:
        from scipy.spatial.distance import pdist, squareform

        self.f_b, self.m, self.metric, self.norm = pool, int(m), metric, norm
        self.distance = get_distance(metric)
        self.fast = metric in ("wasserstein", "euclidean") and norm in ("buffer", "none", "l2")
        if not self.fast:
            return
        x = pool
        if norm == "l2":
            x = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
        self.x = x
        self.pairwise = squareform(pdist(x))  # (n, n), zero diagonal
        self.row_sums = self.pairwise.sum(axis=1)
        self.total = float(self.row_sums.sum())  # twice the sum over pairs
        self.col_sum = x.sum(axis=0)
        self.max_abs = float(np.abs(x).max())
        n, m = len(x), self.m
        self.k = n - m
        self.a = np.full(m, 1.0 / m)
        self.b = np.full(self.k, 1.0 / self.k)

    def __call__(self, idx: np.ndarray) -> float:
        m = self.m
        o_idx, b_idx = idx[:m], idx[m:]
        if not self.fast:
            return self.distance(*normalize_pair(self.f_b[o_idx], self.f_b[b_idx], self.norm))
        scale = 1.0
        if self.norm == "buffer":
            k = self.k
            # sum over ordered pairs inside B' = all - 2 * (rows of O') + (pairs inside O')
            inside = self.total - 2.0 * float(self.row_sums[o_idx].sum())
            inside += float(self.pairwise[np.ix_(o_idx, o_idx)].sum())
            scale = inside / (k * (k - 1)) if k >= 2 else 0.0
            if scale <= 1e-12 * (1.0 + self.max_abs):  # degenerate buffer: normalize_pair's fallback
                return self.distance(*normalize_pair(self.f_b[o_idx], self.f_b[b_idx], self.norm))
        if self.metric == "euclidean":
            o_sum = self.x[o_idx].sum(axis=0)
            diff = o_sum / m - (self.col_sum - o_sum) / self.k
            return float(np.linalg.norm(diff)) / scale
        cost = self.pairwise[np.ix_(o_idx, b_idx)] / scale
        return max(transport_cost(self.a, self.b, cost, max(100_000, 50 * m * self.k)), 0.0)


def max_draws(rate: float, samples: int) -> int:
    """The number of null draws ``N`` of a test at ``rate``: ``samples``, raised to
    ``ceil(1 / rate) - 1`` where that is more, so that ``1 / (1 + N) <= rate`` (the rate is
    attainable). 999 at the defaults (rate 0.001, 200 samples)."""
    return max(int(samples), math.ceil(1.0 / rate - 1e-9) - 1)


def accepts(exceedances: int, draws: int, rate: float) -> bool:
    """The decision of a test with ``draws`` draws once ``exceedances`` of them reached the
    observed distance: accepted when ``(1 + exceedances) / (1 + draws) > rate`` (further draws
    cannot lower its p-value to the rate)."""
    return (1 + exceedances) / (1 + draws) > rate


def splits_suffice(m: int, n: int, draws: int) -> bool:
    """Whether a pool of ``m + n`` vectors has enough distinct splits for a test with ``draws``
    draws: at least ``10 * draws``. With fewer, draws repeat the observed split itself (a tie,
    which counts against ``O``) often enough to cap the test's power: the chance that none of the
    draws repeats it is about ``exp(-draws / splits)``, at least 0.9 here."""
    return math.comb(m + n, m) >= 10 * draws


def null_split(rng: np.random.Generator, m: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """One null draw: pool indices of the ``m`` vectors that play ``O`` and of the ``n`` that play
    ``B_i`` (drawn without replacement from the pool ``0 .. m + n - 1``)."""
    idx = rng.permutation(m + n)
    return idx[:m], idx[m:]


@dataclass
class PermutationResult:
    """One policy's permutation test: ``draws`` made, ``exceedances`` (null >= observed),
    ``p_value = (1 + exceedances) / (1 + draws)`` and the decision ``accepted`` (that of the test
    with all ``max_draws`` draws: ``(1 + exceedances) / (1 + max_draws) > rate``)."""

    draws: int
    exceedances: int
    p_value: float
    accepted: bool


def permutation_test(
    f_o: np.ndarray,
    f_b: np.ndarray,
    metric: str,
    norm: str,
    rate: float,
    draws: int,
    rng: np.random.Generator,
) -> PermutationResult:
    """The exact test of "``O`` and ``B_i`` come from one distribution" (module doc).

    The observed statistic is the distance between the pool's first ``|O|`` and last ``|B_i|``
    vectors, computed by the same function as the null draws. ``O`` is rejected when
    ``(1 + exceedances) / (1 + draws) <= rate`` after all ``draws`` draws; the draws stop at the
    first exceedance that makes this impossible (acceptance is then settled), so under the null a
    test costs few draws (about ``ln(draws) + 0.6`` at the default rate) and a rejection costs all
    of them. Deterministic given ``rng``'s state.
    """
    m, n = len(f_o), len(f_b)
    null = NullDistance(np.concatenate([f_o, f_b]), m, metric, norm)
    observed = null(np.arange(m + n))
    bar = observed - 1e-9 * (1.0 + abs(observed))  # ties (to rounding) count as exceedances
    count = drawn = 0
    while drawn < draws:
        o_idx, b_idx = null_split(rng, m, n)
        drawn += 1
        if null(np.concatenate([o_idx, b_idx])) >= bar:
            count += 1
            if accepts(count, draws, rate):
                break  # accepted whatever the remaining draws give
    return PermutationResult(
        draws=drawn,
        exceedances=count,
        p_value=(1 + count) / (1 + drawn),
        accepted=accepts(count, draws, rate),
    )
