"""Import escnn once, quietly, with one compatibility fix for the pinned scikit-learn and an
in-memory cache in front of escnn's on-disk Clebsch-Gordan cache.

escnn 1.0.11 solves for its steerable kernel bases with ``sklearn.utils.extmath.randomized_svd``
on an ``np.matrix``; scikit-learn >= 1.2 rejects ``np.matrix`` inputs, so building any
convolution between non-trivial representations fails with a ``TypeError``. escnn falls back to
an exact ``scipy.linalg.svd`` when scikit-learn is absent; this module selects that fallback (it
asks for all singular values anyway, so the exact SVD gives the same null space, more accurately).

Every convolution escnn builds asks for Clebsch-Gordan coefficients and tensor decompositions,
which escnn keeps in a joblib cache on disk: each call hashes its arguments and unpickles a file
(~1.6 ms; about half of building one of our networks). The same values are kept here in memory
as well, per process, so the second and later networks of a process (every Trainer, learner and
evaluation after the first) skip the disk. The values are exactly those joblib returns; arrays are
handed out as copies, so a caller that writes into one cannot change the cache.
"""

from __future__ import annotations

import copy
import functools
from typing import Any, Callable

import numpy as np

from .._imports import import_lightly

__all__ = ["import_escnn_nn"]

_PATCHED = False


def import_escnn_nn() -> Any:
    """``escnn.nn``, imported with warnings silenced and the SVD fallback selected."""
    global _PATCHED
    enn = import_lightly("escnn.nn")  # without scikit-learn: escnn's fallback, set below anyway
    import escnn.group._numerical as numerical

    if not _PATCHED:
        numerical.randomized_svd = None
        _remember_clebsch_gordan()
        _PATCHED = True
    return enn


def _remember_clebsch_gordan() -> None:
    import escnn.group._clebsh_gordan as cg

    for name in ("_clebsh_gordan_tensor", "_find_tensor_decomposition"):
        fn = getattr(cg, name)
        if not getattr(fn, "_covers_in_memory", False):
            setattr(cg, name, _in_memory(fn))


def _in_memory(fn: Callable[..., Any]) -> Callable[..., Any]:
    values: dict[Any, Any] = {}

    @functools.wraps(fn)
    def cached(*args: Any, **kwargs: Any) -> Any:
        try:
            key = (args, tuple(sorted(kwargs.items())))
            hash(key)
        except TypeError:  # an unhashable group key: no memory for this call
            return fn(*args, **kwargs)
        if key not in values:
            values[key] = fn(*args, **kwargs)
        value = values[key]
        return value.copy() if isinstance(value, np.ndarray) else copy.deepcopy(value)

    cached._covers_in_memory = True  # type: ignore[attr-defined]
    return cached
