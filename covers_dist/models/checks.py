"""Equivariance check: transform the inputs by every group element and compare the outputs.

For an equivariant actor-critic and every ``g``: ``mean(g.obs) = g.mean(obs)`` (planar action
pairs rotate/mirror, the rest is unchanged), ``log_std(g.obs) = log_std(obs)``,
``value(g.obs) = value(obs)`` and ``features(g.obs) = features(obs)``. Observations are moved
with the same functions the tasks use (:func:`covers_dist.envs.layout.transform_obs`), so the
network and the environments are checked against one convention.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import torch

from ..envs.layout import transform_obs
from ..symmetry import GroupElement, get_group

if TYPE_CHECKING:  # pragma: no cover
    from .actor_critic import ActorCritic

__all__ = ["PROBE_TOLERANCE", "check_same_function", "equivariance_errors", "relative_error", "same_function"]

#: Largest relative difference between two processes' probe outputs still taken as the same function
#: (float rounding across thread counts is ~1e-6; a different escnn basis differs by ~1e-1).
PROBE_TOLERANCE = 1e-4


def relative_error(actual: np.ndarray, expected: np.ndarray) -> float:
    """``max |actual - expected| / max |expected|`` (absolute when ``expected`` is all zeros)."""
    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    scale = float(np.max(np.abs(expected))) if expected.size else 0.0
    diff = float(np.max(np.abs(actual - expected))) if expected.size else 0.0
    return diff / scale if scale > 0 else diff


def _outputs(model: "ActorCritic", obs: Mapping[str, np.ndarray], fast: bool) -> dict[str, np.ndarray]:
    if fast:
        actions, _, values = model.act(obs, deterministic=True)
        return {"mean": actions, "value": values, "features": model.features_np(obs)}
    tens = {"image": torch.from_numpy(np.ascontiguousarray(obs["image"])), "proprio": torch.from_numpy(obs["proprio"])}
    with torch.no_grad():
        mean, log_std, value = model(tens)
        feats = model.features(tens)
    return {"mean": mean.numpy(), "log_std": log_std.numpy(), "value": value.numpy(), "features": feats.numpy()}


def equivariance_errors(
    model: "ActorCritic",
    obs: Mapping[str, Any],
    group: str | None = None,
    fast: bool = False,
) -> dict[str, dict[str, float]]:
    """Relative errors ``{element name: {"mean", "log_std", "value", "features"}}`` on a batch.

    ``obs`` is a batched numpy observation dict laid out as ``model.layout``. ``group`` defaults
    to the model's own group (the CNN twin: D4). The model runs in its current train/eval mode;
    with ``fast`` the exported inference path (``act`` / ``features_np``) is checked instead.
    """
    layout = model.layout
    obs = {"image": np.asarray(obs["image"], np.uint8), "proprio": np.asarray(obs["proprio"], np.float32)}
    if group is None:
        core_group = getattr(model.core, "group", None)
        group = core_group.name if core_group is not None else "D4"
    base = _outputs(model, obs, fast)
    errors: dict[str, dict[str, float]] = {}
    for g in get_group(group):
        moved = _outputs(model, transform_obs(layout, g, obs), fast)
        expected = dict(base, mean=layout.transform_action(g, base["mean"]))
        errors[g.name] = {key: relative_error(moved[key], expected[key]) for key in moved}
    return errors


def max_error(errors: dict[str, dict[str, float]], skip_identity: bool = True) -> float:
    """The largest error in an :func:`equivariance_errors` result."""
    e = GroupElement().name
    return max(v for name, row in errors.items() if not (skip_identity and name == e) for v in row.values())


def same_function(out: Any, ref: Any) -> bool:
    """Whether two :meth:`ActorCritic.probe_outputs` arrays show the same function (same shape,
    relative difference within :data:`PROBE_TOLERANCE`)."""
    out, ref = np.asarray(out, np.float64), np.asarray(ref, np.float64)
    return out.shape == ref.shape and relative_error(out, ref) <= PROBE_TOLERANCE


def check_same_function(probes: Mapping[str, np.ndarray]) -> None:
    """Raise ``RuntimeError`` unless every process's :meth:`ActorCritic.probe_outputs` matches the first.

    ``probes`` maps a process's name (``"rollout worker 0"``, ``"learner of policy 2"``) to its
    probe outputs. Processes that read the same weights as different functions would sample with
    one policy and update another, so a run refuses to go on.
    """
    items = list(probes.items())
    if len(items) < 2:
        return
    ref_name, ref = items[0]
    for name, out in items[1:]:
        out = np.asarray(out, np.float64)
        if out.shape != np.shape(ref):
            raise RuntimeError(
                f"{name} builds a different network from {ref_name}: probe shapes {out.shape} vs {np.shape(ref)}"
            )
        if not same_function(out, ref):
            err = relative_error(out, ref)
            raise RuntimeError(
                f"{name} and {ref_name} compute different functions of the same weights (relative difference "
                f"{err:.2g} > {PROBE_TOLERANCE:g}): a constant of the network is built differently per process "
                f"(e.g. a change of basis drawn from a random state), so workers would sample with another policy "
                f"than the learner updates"
            )
