"""Import escnn once, quietly, with one compatibility fix for the pinned scikit-learn.

escnn 1.0.11 solves for its steerable kernel bases with ``sklearn.utils.extmath.randomized_svd``
on an ``np.matrix``; scikit-learn >= 1.2 rejects ``np.matrix`` inputs, so building any
convolution between non-trivial representations fails with a ``TypeError``. escnn falls back to
an exact ``scipy.linalg.svd`` when scikit-learn is absent; this module selects that fallback (it
asks for all singular values anyway, so the exact SVD gives the same null space, more accurately).
"""

from __future__ import annotations

import warnings
from typing import Any

__all__ = ["import_escnn_nn"]

_PATCHED = False


def import_escnn_nn() -> Any:
    """``escnn.nn``, imported with warnings silenced and the SVD fallback selected."""
    global _PATCHED
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import escnn.group._numerical as numerical
        from escnn import nn as enn
    if not _PATCHED:
        numerical.randomized_svd = None
        _PATCHED = True
    return enn
