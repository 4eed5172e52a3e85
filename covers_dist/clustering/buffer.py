"""A policy's buffer ``B_i`` of raw initial observations, capped with a replacement rule.

The buffer holds raw observations ``{"image": uint8 (n, S, S, 3), "proprio": float32 (n, P)}``
(not features: a policy's own encoder changes while it trains, so features are recomputed from
the raw frames at every assignment). It keeps at most ``capacity`` frames. When it is full, a new
frame is admitted by one of two rules:

* ``reservoir`` (default): reservoir sampling (Vitter's algorithm R). The ``t``-th frame ever
  offered (1-based) replaces a uniformly chosen slot with probability ``capacity / t``, so the
  buffer is at all times a uniform sample of every frame the policy was assigned, old tasks of
  its group included. Randomness comes from the buffer's own seeded generator
  (``numpy.random.Generator(PCG64(seed))``); its state is saved with the bank, so a restored bank
  continues exactly as the original would have.
* ``fifo``: first in, first out; the buffer holds the ``capacity`` most recent frames.

Frame order inside the buffer carries no meaning (the distances compare sets).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["ObservationBuffer", "REPLACEMENT_RULES", "check_obs"]

REPLACEMENT_RULES: tuple[str, ...] = ("reservoir", "fifo")


def check_obs(obs: Any, what: str = "obs") -> int:
    """Validate an observation batch ``{"image": uint8 (n,S,S,3), "proprio": float32 (n,P)}``; return n."""
    if not isinstance(obs, dict) or set(obs) != {"image", "proprio"}:
        keys = sorted(obs) if isinstance(obs, dict) else type(obs).__name__
        raise TypeError(f"{what} must be a dict with keys ['image', 'proprio'], got {keys}")
    image, proprio = obs["image"], obs["proprio"]
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 4 or image.shape[-1] != 3:
        desc = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"{what}['image'] must be a uint8 array of shape (n, S, S, 3), got {desc}")
    if image.shape[1] != image.shape[2]:
        raise ValueError(f"{what}['image'] must hold square frames, got shape {image.shape}")
    if not isinstance(proprio, np.ndarray) or proprio.ndim != 2 or not np.issubdtype(proprio.dtype, np.floating):
        desc = f"{proprio.dtype} {proprio.shape}" if isinstance(proprio, np.ndarray) else type(proprio).__name__
        raise ValueError(f"{what}['proprio'] must be a float array of shape (n, P), got {desc}")
    if image.shape[0] != proprio.shape[0]:
        raise ValueError(f"{what}: image has {image.shape[0]} frames but proprio has {proprio.shape[0]}")
    if image.shape[0] < 1:
        raise ValueError(f"{what} must hold at least one frame")
    if not np.all(np.isfinite(proprio)):
        raise ValueError(f"{what}['proprio'] contains NaN or infinite values")
    return int(image.shape[0])


class ObservationBuffer:
    """At most ``capacity`` raw initial frames, admitted by ``rule`` (``reservoir`` or ``fifo``)."""

    def __init__(self, capacity: int, rule: str = "reservoir", seed: int = 0) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, (int, np.integer)) or capacity < 1:
            raise ValueError(f"buffer capacity must be an integer >= 1, got {capacity!r}")
        if rule not in REPLACEMENT_RULES:
            raise ValueError(f"buffer replacement rule must be one of {list(REPLACEMENT_RULES)}, got {rule!r}")
        self.capacity = int(capacity)
        self.rule = rule
        self.rng = np.random.Generator(np.random.PCG64(seed))
        self.seen = 0  # frames ever offered
        self.size = 0  # frames held
        self._next = 0  # fifo write position
        self._image: np.ndarray | None = None
        self._proprio: np.ndarray | None = None

    def __len__(self) -> int:
        return self.size

    def _allocate(self, obs: dict[str, np.ndarray]) -> None:
        s, p = obs["image"].shape[1], obs["proprio"].shape[1]
        self._image = np.zeros((self.capacity, s, s, 3), dtype=np.uint8)
        self._proprio = np.zeros((self.capacity, p), dtype=np.float32)

    def add(self, obs: dict[str, np.ndarray]) -> None:
        """Offer every frame of ``obs`` (in order) to the buffer."""
        n = check_obs(obs)
        if self._image is None:
            self._allocate(obs)
        assert self._image is not None and self._proprio is not None
        if obs["image"].shape[1:] != self._image.shape[1:] or obs["proprio"].shape[1] != self._proprio.shape[1]:
            raise ValueError(
                f"observation shapes {obs['image'].shape[1:]} / proprio {obs['proprio'].shape[1]} differ from "
                f"the buffer's {self._image.shape[1:]} / proprio {self._proprio.shape[1]}"
            )
        for i in range(n):
            self.seen += 1
            if self.size < self.capacity:
                slot = self.size
                self.size += 1
            elif self.rule == "fifo":
                slot = self._next
            else:
                j = int(self.rng.integers(0, self.seen))
                if j >= self.capacity:
                    continue
                slot = j
            if self.rule == "fifo":
                self._next = (slot + 1) % self.capacity
            self._image[slot] = obs["image"][i]
            self._proprio[slot] = obs["proprio"][i]

    def observations(self) -> dict[str, np.ndarray]:
        """The held frames as an observation batch (views; do not modify)."""
        if self._image is None or self._proprio is None:
            raise ValueError("the buffer is empty")
        return {"image": self._image[: self.size], "proprio": self._proprio[: self.size]}

    # ---- persistence ----------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """JSON-safe bookkeeping (the arrays are saved separately, see :meth:`observations`)."""
        return {
            "capacity": self.capacity,
            "rule": self.rule,
            "seen": self.seen,
            "size": self.size,
            "next": self._next,
            "rng": self.rng.bit_generator.state,
        }

    @classmethod
    def from_state(cls, state: dict[str, Any], image: np.ndarray, proprio: np.ndarray) -> "ObservationBuffer":
        """Rebuild a buffer from :meth:`state` and its held frames."""
        buf = cls(int(state["capacity"]), str(state["rule"]))
        buf.rng.bit_generator.state = state["rng"]
        buf.seen, buf.size, buf._next = int(state["seen"]), int(state["size"]), int(state["next"])
        if image.shape[0] != buf.size or proprio.shape[0] != buf.size or buf.size > buf.capacity:
            raise ValueError(
                f"buffer arrays hold {image.shape[0]} / {proprio.shape[0]} frames, state says {buf.size} "
                f"(capacity {buf.capacity})"
            )
        if buf.size:
            buf._allocate({"image": image, "proprio": proprio})
            assert buf._image is not None and buf._proprio is not None
            buf._image[: buf.size] = image
            buf._proprio[: buf.size] = proprio
        return buf
