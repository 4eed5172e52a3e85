"""Where the bank's features come from, and how they are normalized.

The bank never imports torch: it receives features through a callable.

* **Own encoder** (``clustering.feature_source: own``, the paper's choice): a
  ``FeatureFn = (policy_id, obs) -> (n, F)`` array that runs policy ``policy_id``'s own network
  (its group-pooled invariant features, ``model.features_np(obs)``) on a raw observation batch.
  ``O`` and ``B_i`` are both encoded by policy ``i``'s current weights, so the comparison follows
  the policy as it trains, and each policy judges "is this my kind of task" in its own terms.
  Cost: one encoder pass over ``O`` and ``B_i`` per policy per assignment.
* **Shared encoder** (``feature_source: shared``): one frozen encoder for every policy, wrapped
  with :class:`SharedFeatures` (``fn(obs) -> (n, F)``). ``O`` is encoded once per assignment and
  every distance is measured in the same feature space, so one threshold means the same thing for
  all policies; the features do not improve with training.
* **Colour histogram** (``feature_source: colors``): no network. Each frame's pixels are
  quantised to ``levels`` values per channel and counted into ``levels**3`` bins; the feature is
  the square root of each bin's share of the frame (:func:`color_histogram`). Counting pixels
  ignores where they are, so the feature is exactly invariant to any rotation or mirror image of
  the frame (any permutation of its pixels), and it is fixed: it neither trains nor drifts. It
  tells task groups apart by the colours of their objects, not by their layout.

Normalization (``clustering.feature_norm``), applied to the pair (features of ``O``, features of
``B_i``) before a distance:

* ``buffer`` (default): both sets divided by the mean pairwise Euclidean distance between the
  buffer's own feature vectors. Distances are then in units of the buffer's spread, whatever the
  scale of an encoder's activations (untrained encoders, encoders of different policies, and one
  encoder as its weights grow in training all give comparable numbers), and the paper's
  ``d_eps = 1.0`` for W1 reads: "O is farther from B, in the optimal-transport sense, than two
  random members of B are from each other". When the buffer has fewer than two distinct feature
  vectors, the mean pairwise distance over ``O`` and ``B`` together is used (and when that is
  zero too, the sets are identical and every distance is 0). The Mahalanobis distance is
  scale-invariant and unaffected.
* ``none``: raw features (the paper's setting; thresholds then depend on the encoder's scale).
* ``l2``: each row scaled to unit Euclidean norm (W1 and the mean distance lie in [0, 2]).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = [
    "FeatureFn", "SharedFeatures", "FEATURE_NORMS", "normalize_pair", "check_features", "color_histogram",
    "COLOR_LEVELS",
]  # fmt: skip

FeatureFn = Callable[[int, dict[str, np.ndarray]], np.ndarray]
FEATURE_NORMS: tuple[str, ...] = ("buffer", "none", "l2")


class SharedFeatures:
    """Wraps one encoder ``fn(obs) -> (n, F)`` as a :data:`FeatureFn` shared by every policy."""

    shared = True

    def __init__(self, fn: Callable[[dict[str, np.ndarray]], np.ndarray]) -> None:
        if not callable(fn):
            raise TypeError(f"SharedFeatures needs a callable, got {type(fn).__name__}")
        self.fn = fn

    def __call__(self, policy_id: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self.fn(obs)


#: Quantisation levels per colour channel of :func:`color_histogram` (4**3 = 64 bins).
COLOR_LEVELS = 4


def color_histogram(obs: dict[str, np.ndarray], levels: int = COLOR_LEVELS) -> np.ndarray:
    """``(n, levels**3)`` square-rooted colour shares of the frames ``obs["image"]`` (n, H, W, 3) uint8.

    Exactly invariant to every permutation of a frame's pixels (so to D4 acting on the image).
    The square root (the Hellinger embedding) lets the few pixels of a small object count
    beside the table's many."""
    images = np.asarray(obs["image"])
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"color_histogram needs uint8 frames of shape (n, H, W, 3), got {images.dtype} {images.shape}")
    if not isinstance(levels, int) or not 2 <= levels <= 16:
        raise ValueError(f"levels must be an integer in 2..16, got {levels!r}")
    q = images.astype(np.int64) * levels // 256
    bins = ((q[..., 0] * levels + q[..., 1]) * levels + q[..., 2]).reshape(len(images), -1)
    n_bins = levels**3
    offsets = np.arange(len(images))[:, None] * n_bins
    counts = np.bincount((bins + offsets).ravel(), minlength=len(images) * n_bins).reshape(len(images), n_bins)
    return np.sqrt(counts / bins.shape[1])


def check_features(x: object, n: int, policy_id: int) -> np.ndarray:
    """Validate a feature callable's output: an (n, F) finite real array; returned as float64."""
    if not isinstance(x, np.ndarray):
        raise TypeError(f"feature function for policy {policy_id} returned {type(x).__name__}, expected a numpy array")
    if x.ndim != 2 or x.shape[0] != n or x.shape[1] < 1:
        raise ValueError(f"feature function for policy {policy_id} returned shape {x.shape}, expected ({n}, F)")
    x = x.astype(np.float64, copy=False)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"feature function for policy {policy_id} returned NaN or infinite values")
    return x


def _mean_pairwise_distance(x: np.ndarray) -> float:
    from scipy.spatial.distance import pdist

    return float(pdist(x).mean()) if x.shape[0] >= 2 else 0.0


def normalize_pair(f_o: np.ndarray, f_b: np.ndarray, norm: str) -> tuple[np.ndarray, np.ndarray]:
    """Apply the feature normalization ``norm`` (one of :data:`FEATURE_NORMS`) to (O, B) features."""
    if norm == "none":
        return f_o, f_b
    if norm == "l2":
        def unit(x: np.ndarray) -> np.ndarray:
            return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)

        return unit(f_o), unit(f_b)
    if norm == "buffer":
        scale = _mean_pairwise_distance(f_b)
        if scale <= 1e-12 * (1.0 + float(np.abs(f_b).max())):
            scale = _mean_pairwise_distance(np.concatenate([f_o, f_b]))
        if scale <= 0.0:
            return f_o, f_b
        return f_o / scale, f_b / scale
    raise ValueError(f"feature_norm must be one of {list(FEATURE_NORMS)}, got {norm!r}")
