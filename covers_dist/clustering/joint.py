"""Joint features: every policy's learned invariant features of a frame, side by side.

``clustering.feature_source: joint``. The feature of a frame is the concatenation, over the
bank's policies ``p`` in id order, of ``phi_p(x) / ||phi_p(x)||``: policy ``p``'s own
group-pooled (invariant) encoder output scaled to unit length. Every distance of an assignment
is measured in this one space, for every policy's buffer alike, so:

* what any policy has learned to see counts for every comparison: a Goal Reach policy whose
  encoder ignores the drawer does not make Drawer Close frames look like its own buffer, since
  the Drawer Close policy's block tells them apart;
* one threshold (and one null distribution per buffer) means the same thing for all policies;
* each block is exactly invariant to the group (its encoder is), so the concatenation is too;
* unit-length blocks keep one policy's activation scale (which grows as it trains) from
  drowning the others; the bank's ``feature_norm`` then scales the pair by the buffer's spread.

The space moves when a policy trains or joins the bank; the calibrated rule draws its null in
the space of the moment, so a move shifts the observed distance and its null together.

Cost: each encoder sees each frame once per weights version. Features are cached per (policy,
version, frame digest), so an assignment after one policy's update re-encodes the buffers with
that policy's encoder only and encodes the new frames with the others. Plain Python: the
encoders are callables given by the caller (no torch import here).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import Callable, Mapping

import numpy as np

__all__ = ["JointFeatures", "EncoderMap"]

#: ``() -> {policy id: (weights version, encoder)}``; ``encoder(obs) -> (n, F)`` numpy features.
EncoderMap = Callable[[], Mapping[int, tuple[int, Callable[[dict[str, np.ndarray]], np.ndarray]]]]


def _digests(obs: dict[str, np.ndarray]) -> list[bytes]:
    images, proprio = np.ascontiguousarray(obs["image"]), np.ascontiguousarray(obs["proprio"])
    out = []
    for i in range(len(images)):
        h = hashlib.blake2b(images[i].tobytes(), digest_size=16)
        h.update(proprio[i].tobytes())
        out.append(h.digest())
    return out


class JointFeatures:
    """A shared :data:`~covers_dist.clustering.features.FeatureFn`: the unit-length invariant
    features of every encoder of ``encoders()``, concatenated in policy-id order.

    ``cache_frames``: feature vectors kept per policy (least recently used dropped first)."""

    shared = True

    def __init__(self, encoders: EncoderMap, cache_frames: int = 4096) -> None:
        if not callable(encoders):
            raise TypeError(f"JointFeatures needs a callable returning the encoders, got {type(encoders).__name__}")
        if not isinstance(cache_frames, int) or cache_frames < 0:
            raise ValueError(f"cache_frames must be an integer >= 0, got {cache_frames!r}")
        self.encoders = encoders
        self.cache_frames = cache_frames
        self._cache: dict[int, tuple[int, OrderedDict[bytes, np.ndarray]]] = {}
        self.encoded_frames = 0  # frames run through an encoder (not served from the cache)

    def block(self, policy_id: int, version: int, encoder: Callable, obs: dict[str, np.ndarray]) -> np.ndarray:
        """``(n, F_p)`` unit-length features of policy ``policy_id``'s encoder (cached by version)."""
        n = len(obs["image"])
        cached_version, cache = self._cache.get(policy_id, (None, OrderedDict()))
        if cached_version != version:
            cache = OrderedDict()
        keys = _digests(obs)
        missing = [i for i, k in enumerate(keys) if k not in cache]
        if missing:
            part = {k: np.asarray(v)[missing] for k, v in obs.items() if k in ("image", "proprio")}
            raw = np.asarray(encoder(part), dtype=np.float64)
            if raw.ndim != 2 or raw.shape[0] != len(missing):
                raise ValueError(f"encoder of policy {policy_id} returned shape {raw.shape} for {len(missing)} frames")
            unit = raw / np.maximum(np.linalg.norm(raw, axis=1, keepdims=True), 1e-12)
            self.encoded_frames += len(missing)
            for i, row in zip(missing, unit):
                cache[keys[i]] = row
        rows = []
        for k in keys:
            cache.move_to_end(k)
            rows.append(cache[k])
        while len(cache) > self.cache_frames:
            cache.popitem(last=False)
        self._cache[policy_id] = (version, cache)
        return np.stack(rows) if rows else np.zeros((n, 0))

    def __call__(self, policy_id: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        encoders = dict(self.encoders())
        if not encoders:
            raise LookupError("joint features need at least one policy's encoder")
        for pid in list(self._cache):
            if pid not in encoders:
                del self._cache[pid]
        blocks = [self.block(pid, int(v), fn, obs) for pid, (v, fn) in sorted(encoders.items())]
        return np.concatenate(blocks, axis=1)
