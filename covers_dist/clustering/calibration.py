"""The null distribution of the calibrated rule: ``d(O', B minus O')`` for random subsets ``O'``.

:class:`NullDistance` holds one policy's buffer features ``f_b`` (computed once per assignment)
and returns the distance between a subset ``O' = f_b[idx[:m]]`` and the rest ``f_b[idx[m:]]``,
with the bank's metric and feature normalization. For W1 and the mean Euclidean distance under
the ``buffer``, ``none`` and ``l2`` normalizations it reuses the buffer's pairwise distance matrix
(computed once) instead of recomputing ``pdist`` and ``cdist`` per subset: the result equals
``distance(*normalize_pair(O', B', norm))`` up to rounding (tested). Other cases (Mahalanobis, a
buffer whose spread is zero) take that generic path.
"""

from __future__ import annotations

import numpy as np

from .distances import get_distance
from .features import normalize_pair

__all__ = ["NullDistance"]


class NullDistance:
    """``d(f_b[idx[:m]], f_b[idx[m:]])`` for index permutations ``idx`` of one buffer's features."""

    def __init__(self, f_b: np.ndarray, m: int, metric: str, norm: str) -> None:
        from scipy.spatial.distance import pdist, squareform

        self.f_b, self.m, self.metric, self.norm = f_b, int(m), metric, norm
        self.distance = get_distance(metric)
        self.fast = metric in ("wasserstein", "euclidean") and norm in ("buffer", "none", "l2")
        if not self.fast:
            return
        x = f_b
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
        import ot

        cost = self.pairwise[np.ix_(o_idx, b_idx)] / scale
        value = ot.emd2(self.a, self.b, cost, numItermax=max(100_000, 50 * m * self.k))
        return max(float(value), 0.0)
