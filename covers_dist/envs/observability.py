"""Is a task observable? A check over many seeded resets of one environment.

A task is observable when everything that decides success can be read from the first
observation. Over ``num_resets`` seeded resets this module records the first observation (image
bytes and proprio) and the positions that decide success (``env.task_state()``, base frame) and
flags two kinds of violation:

- collisions: two resets (of ``env``, or of ``env`` and a ``twin`` reset with the same seeds)
  whose first images and proprio are identical while a success-relevant position differs (by
  more than ``position_tol``); no policy can tell them apart, yet they may need different
  actions. Positions at the same height whose (x, y) are closer than the image's
  ``resolution`` (one pixel, ``env.view.pitch``, by default) can give the same pixels however
  observable the task is: such collisions are image quantization, counted but not violations;
- hidden heights: a success-relevant position whose z differs between resets (spread above
  ``z_tol``); a top-down orthographic image cannot show z, so a varying z is hidden even when
  each image differs (placements are continuous, so exact collisions are rare and this is the
  decisive test).

A ``twin`` is the same task with hidden coordinates drawn differently (e.g. the goal's height):
resetting both with the same seed and pooling their records checks directly that what is hidden
changes no pixel. The environment is duck-typed: ``reset(seed=...) -> (obs, info)`` with
``obs["image"]`` and ``obs["proprio"]``, and ``task_state() -> {name: xyz}`` (``name_base`` in
the base frame when present). numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Collision", "ObservabilityReport", "check_observability"]

#: Default tolerances (metres): positions equal up to ``POSITION_TOL``; z spread allowed ``Z_TOL``.
POSITION_TOL = 1e-9
Z_TOL = 1e-6


@dataclass(frozen=True)
class Collision:
    """Two resets with the same first observation but different success-relevant positions."""

    first: str  # "seed 12" or "twin seed 12"
    second: str
    key: str
    distance: float  # metres between the two positions of ``key``
    subpixel: bool = False  # same z, (x, y) closer than one pixel: quantization, not hidden state

    def __str__(self) -> str:
        tail = " (below one pixel)" if self.subpixel else ""
        return f"{self.first} and {self.second}: same first observation, {self.key} differs by {self.distance:.4g} m{tail}"


@dataclass
class ObservabilityReport:
    """What :func:`check_observability` found; ``ok`` when nothing hidden decides success."""

    task: str
    num_resets: int
    keys: tuple[str, ...]
    #: per success-relevant position: max - min of its z over all resets (metres)
    z_spread: dict[str, float] = field(default_factory=dict)
    #: per success-relevant position: the larger of the x and y spreads (how much placements vary)
    xy_spread: dict[str, float] = field(default_factory=dict)
    #: how many different first observations (image and proprio) the resets gave
    distinct_observations: int = 0
    #: metres below which a collision is image quantization (one pixel)
    resolution: float = 0.0
    #: every collision found, sub-pixel ones included
    collisions: list[Collision] = field(default_factory=list)
    violations: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.violations

    def __str__(self) -> str:
        head = f"{self.task}: {'observable' if self.ok else 'NOT observable'} over {self.num_resets} resets"
        lines = [head, f"  distinct first observations: {self.distinct_observations}"]
        for key in self.keys:
            lines.append(f"  {key}: z spread {self.z_spread[key]:.3g} m, xy spread {self.xy_spread[key]:.3g} m")
        subpixel = sum(c.subpixel for c in self.collisions)
        lines.append(
            f"  collisions: {len(self.collisions) - subpixel}"
            f" (+{subpixel} closer than one pixel, {self.resolution:.3g} m: image quantization)"
        )
        lines.extend(f"  violation: {v}" for v in self.violations)
        return "\n".join(lines)


def _success_keys(env: Any, keys: tuple[str, ...] | None) -> tuple[str, ...]:
    if keys is not None:
        return tuple(keys)
    spec = getattr(env, "spec_entry", None)
    found = getattr(spec, "success_state", None)
    if not found:
        raise ValueError("pass keys=...: the env's spec names no success_state")
    return tuple(found)


def _record(env: Any, seed: int, keys: tuple[str, ...]) -> tuple[bytes, dict[str, np.ndarray]]:
    obs, _ = env.reset(seed=seed)
    image = np.ascontiguousarray(obs["image"])
    proprio = np.ascontiguousarray(np.asarray(obs["proprio"]))
    # the observation, exactly: shapes and dtypes included, so equal bytes mean equal arrays
    parts = [str(image.shape), str(image.dtype), str(proprio.shape), str(proprio.dtype)]
    signature = b"|".join([p.encode() for p in parts] + [image.tobytes(), proprio.tobytes()])
    state = env.task_state()
    positions = {}
    for key in keys:
        name = f"{key}_base" if f"{key}_base" in state else key
        if name not in state:
            raise KeyError(f"task_state() has no position {key!r} (keys: {sorted(state)})")
        positions[key] = np.array(state[name], dtype=np.float64).reshape(-1)[:3]
    return signature, positions


def check_observability(
    env: Any,
    num_resets: int = 64,
    seed: int = 0,
    *,
    keys: tuple[str, ...] | None = None,
    twin: Any = None,
    position_tol: float = POSITION_TOL,
    z_tol: float = Z_TOL,
    resolution: float | None = None,
    task: str | None = None,
) -> ObservabilityReport:
    """Reset ``env`` with seeds ``seed .. seed + num_resets - 1`` and check that the positions
    that decide success (``keys``, default ``env.spec_entry.success_state``) are visible.

    ``twin``: another env of the same task, reset with the same seeds; its records join the
    collision check (not the spreads, which describe ``env``). ``resolution``: collisions whose
    positions share their z and whose (x, y) are closer than this (metres) are image
    quantization; default one pixel of the env's view (``env.view.pitch``), or 0 without one.
    """
    if isinstance(num_resets, bool) or not isinstance(num_resets, (int, np.integer)) or num_resets < 2:
        raise ValueError(f"num_resets must be an integer >= 2, got {num_resets!r}")
    keys = _success_keys(env, keys)
    name = task or getattr(env, "task", None) or type(env).__name__
    records: list[tuple[str, bytes, dict[str, np.ndarray]]] = []
    for i in range(int(num_resets)):
        s = int(seed) + i
        records.append((f"seed {s}", *_record(env, s, keys)))
        if twin is not None:
            records.append((f"twin seed {s}", *_record(twin, s, keys)))

    if resolution is None:
        resolution = float(getattr(getattr(env, "view", None), "pitch", 0.0))
    report = ObservabilityReport(task=str(name), num_resets=int(num_resets), keys=keys, resolution=resolution)
    own = [positions for label, _, positions in records if not label.startswith("twin")]
    for key in keys:
        pts = np.stack([p[key] for p in own])
        spread = pts.max(axis=0) - pts.min(axis=0)
        report.z_spread[key] = float(spread[2])
        report.xy_spread[key] = float(spread[:2].max())
        if spread[2] > z_tol:
            report.violations.append(
                f"{key}: z varies by {spread[2]:.4g} m across resets (> {z_tol:g}); a top-down image cannot show it"
            )

    groups: dict[bytes, list[int]] = {}
    for index, (_, signature, _) in enumerate(records):
        groups.setdefault(signature, []).append(index)
    report.distinct_observations = len(groups)
    for members in groups.values():
        first_label, _, first_pos = records[members[0]]
        for other in members[1:]:
            label, _, pos = records[other]
            for key in keys:
                diff = pos[key] - first_pos[key]
                distance = float(np.linalg.norm(diff))
                if distance > position_tol:
                    subpixel = abs(diff[2]) <= position_tol and float(np.hypot(diff[0], diff[1])) < resolution
                    report.collisions.append(Collision(first_label, label, key, distance, bool(subpixel)))
    hidden = [c for c in report.collisions if not c.subpixel]
    if hidden:
        worst = max(hidden, key=lambda c: c.distance)
        report.violations.append(f"{len(hidden)} collision(s), e.g. {worst}")
    return report
