"""Distances between two sets of feature vectors, pluggable by name.

Each distance takes ``O`` (m, d) -- features of the new initial observations -- and ``B`` (n, d)
-- features of a policy's buffer -- and returns a non-negative float:

* ``wasserstein``: the exact 1-Wasserstein distance with Euclidean ground cost between the
  uniform empirical distributions of the rows of ``O`` and of ``B`` (POT's network-simplex
  solver ``ot.emd2`` on the matrix of pairwise Euclidean distances). The cost matrix is the one
  ``ot.dist(O, B, metric="euclidean")`` gives -- not POT's default metric, the *squared*
  Euclidean distance, which would give W2 squared -- but computed from per-pair differences
  (``scipy.spatial.distance.cdist``) rather than from the Gram expansion, which leaves residues of
  about 1e-8 on identical points; identical sets then give exactly 0.
* ``euclidean``: the Euclidean distance between the mean vectors of ``O`` and ``B``.
* ``mahalanobis``: the Mahalanobis distance of ``O``'s mean from ``B``'s distribution,
  ``sqrt((mu_O - mu_B)^T S^-1 (mu_O - mu_B))`` with ``S`` a regularized covariance of ``B``:
  Ledoit-Wolf shrinkage towards ``(tr(C) / d) I`` (well conditioned even when n < d), plus a
  ridge ``(RIDGE_REL * tr(C) / d + RIDGE_ABS) I`` so that a buffer of identical points (or of a
  single point) gives a large but finite distance instead of a division by zero.

The module imports numpy, POT and scikit-learn only (no torch): features arrive as arrays.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = [
    "wasserstein1",
    "mean_euclidean",
    "mahalanobis",
    "regularized_covariance",
    "DISTANCES",
    "METRIC_NAMES",
    "get_distance",
    "RIDGE_REL",
    "RIDGE_ABS",
]

#: Relative ridge added to the shrunk covariance: ``RIDGE_REL * tr(C) / d``.
RIDGE_REL = 1e-3
#: Absolute ridge floor (keeps a zero-variance buffer invertible).
RIDGE_ABS = 1e-8

DistanceFn = Callable[[np.ndarray, np.ndarray], float]


def _check_sets(o: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate two feature sets: 2-D, non-empty, same width, finite; returned as float64."""
    arrays = []
    for name, x in (("O", o), ("B", b)):
        if not isinstance(x, np.ndarray):
            raise TypeError(f"feature set {name} must be a numpy array, got {type(x).__name__}")
        if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
            raise ValueError(f"feature set {name} must have shape (n >= 1, d >= 1), got {x.shape}")
        if not np.issubdtype(x.dtype, np.number) or np.issubdtype(x.dtype, np.complexfloating):
            raise TypeError(f"feature set {name} must hold real numbers, got dtype {x.dtype}")
        x = x.astype(np.float64, copy=False)
        if not np.all(np.isfinite(x)):
            raise ValueError(f"feature set {name} contains NaN or infinite values")
        arrays.append(x)
    if arrays[0].shape[1] != arrays[1].shape[1]:
        raise ValueError(f"feature widths differ: O has d={arrays[0].shape[1]}, B has d={arrays[1].shape[1]}")
    return arrays[0], arrays[1]


def wasserstein1(o: np.ndarray, b: np.ndarray) -> float:
    """Exact W1 (Euclidean ground cost) between the uniform empirical distributions of O and B."""
    from scipy.spatial.distance import cdist

    from .._imports import import_lightly

    ot = import_lightly("ot")  # POT: imported here so that merely importing the package stays cheap

    o, b = _check_sets(o, b)
    cost = cdist(o, b, metric="euclidean")
    m, n = cost.shape
    # The network simplex needs at most a few (m + n) pivots per point; the default cap of 1e5
    # iterations can stop early on 512 x 512 problems.
    value = ot.emd2(np.full(m, 1.0 / m), np.full(n, 1.0 / n), cost, numItermax=max(100_000, 50 * m * n))
    return max(float(value), 0.0)


def mean_euclidean(o: np.ndarray, b: np.ndarray) -> float:
    """Euclidean distance between the mean vectors of O and B."""
    o, b = _check_sets(o, b)
    return float(np.linalg.norm(o.mean(axis=0) - b.mean(axis=0)))


def regularized_covariance(b: np.ndarray) -> np.ndarray:
    """Covariance of the rows of ``b``: Ledoit-Wolf shrinkage plus a small ridge (see module doc)."""
    from sklearn.covariance import ledoit_wolf

    n, d = b.shape
    if n >= 2:
        cov, _ = ledoit_wolf(b, assume_centered=False)
    else:
        cov = np.zeros((d, d))
    ridge = RIDGE_REL * float(np.trace(cov)) / d + RIDGE_ABS
    return cov + ridge * np.eye(d)


def mahalanobis(o: np.ndarray, b: np.ndarray) -> float:
    """Mahalanobis distance of O's mean from B's (regularized) distribution."""
    o, b = _check_sets(o, b)
    delta = o.mean(axis=0) - b.mean(axis=0)
    cov = regularized_covariance(b)
    chol = np.linalg.cholesky(cov)  # positive definite by construction (ridge > 0)
    z = np.linalg.solve(chol, delta)
    return float(np.sqrt(z @ z))


#: Distance functions by config name (``clustering.metric``).
DISTANCES: dict[str, DistanceFn] = {
    "wasserstein": wasserstein1,
    "euclidean": mean_euclidean,
    "mahalanobis": mahalanobis,
}
METRIC_NAMES: tuple[str, ...] = tuple(DISTANCES)


def get_distance(name: str) -> DistanceFn:
    """The distance function called ``name`` (one of :data:`METRIC_NAMES`)."""
    if name not in DISTANCES:
        raise ValueError(f"unknown clustering metric {name!r}; expected one of {list(METRIC_NAMES)}")
    return DISTANCES[name]
