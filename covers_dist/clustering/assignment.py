"""The assignment step of COVERS (Algorithm 1): the decision rule and its record.

Given the distances ``d_i`` from the new initial observations ``O`` to every policy's buffer:

* empty bank: **adopt** -- the initial policy (id 0, which already exists before any
  assignment) takes ``O`` as its buffer;
* ``min_i d_i <= threshold``: **recall** the nearest policy ``j = argmin d_i`` (ties: lowest id);
* ``min_i d_i > threshold`` and fewer than ``max_policies`` policies: **new** -- a fresh policy
  entry with buffer ``O``; the caller builds a fresh (randomly initialized) policy for it;
* ``min_i d_i > threshold`` with ``max_policies`` policies already: **recall_at_cap** -- the
  nearest policy is recalled anyway (the bank never grows past its cap, and the nearest policy
  is the best available guess; the record says so, so that a run can report it).

In ground-truth mode (the COVERS-GT baseline) the true group id picks the policy instead: the
first policy of a group is made (``adopt`` / ``new``) the first time the group is met, and later
batches of that group ``recall`` it. No distances are computed in that mode.

The **calibrated** rule (``clustering.rule: calibrated``, :func:`decide_calibrated`) replaces the
fixed threshold by a per-policy test: policy ``i`` *accepts* ``O`` unless an exact permutation
test (``O`` and ``B_i`` pooled and split at random) gives a p-value at or below
``clustering.false_split_rate`` (the bank runs the tests, see
:meth:`~covers_dist.clustering.bank.PolicyBank.calibrated_distances`); the nearest accepting
policy is recalled, and a new policy is made only when every policy rejects (``recall_at_cap``
at the cap, as above).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = ["AssignmentRecord", "DECISIONS", "RULES", "decide", "decide_calibrated"]

#: Every decision an assignment can make.
DECISIONS: tuple[str, ...] = ("adopt", "new", "recall", "recall_at_cap")

#: The decision rules (``clustering.rule``).
RULES: tuple[str, ...] = ("threshold", "calibrated")


def decide(
    distances: dict[int, float], threshold: float, max_policies: int, num_policies: int | None = None
) -> tuple[int | None, str]:
    """Apply the rule above: returns (recalled policy id or None for adopt/new, decision).

    ``num_policies``: the bank's size, when ``distances`` covers only some of its policies (a
    what-if restricted to some policies); default ``len(distances)``.
    """
    if not distances:
        return None, "adopt"
    nearest = min(sorted(distances), key=lambda pid: distances[pid])
    if distances[nearest] <= threshold:
        return nearest, "recall"
    if (len(distances) if num_policies is None else num_policies) >= max_policies:
        return nearest, "recall_at_cap"
    return None, "new"


def decide_calibrated(
    distances: dict[int, float], accepted: dict[int, bool], max_policies: int, num_policies: int | None = None
) -> tuple[int | None, str]:
    """The calibrated rule: recall the nearest policy among those that accept ``O`` (ties: lowest
    id); when none accepts, a new policy (or ``recall_at_cap``, the nearest overall, at the cap;
    ``num_policies`` as in :func:`decide`)."""
    if not distances:
        return None, "adopt"
    order = sorted(sorted(distances), key=lambda pid: distances[pid])
    for pid in order:
        if accepted[pid]:
            return pid, "recall"
    if (len(distances) if num_policies is None else num_policies) >= max_policies:
        return order[0], "recall_at_cap"
    return None, "new"


def _json_float(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


@dataclass
class AssignmentRecord:
    """What one assignment decided, and why.

    ``distances`` maps every policy id present before the decision to its distance (empty for an
    adopt and in ground-truth mode). ``new`` is True when the call created a bank entry (adopt or
    new); only ``decision == "new"`` asks the caller for a fresh policy. ``true_groups`` holds the
    true group id of each covered episode when the caller gave them (metrics only).

    Calibrated rule only (both None under the threshold rule, and then left out of
    :meth:`to_dict`, so threshold records and older saved histories read as before):
    ``p_values`` maps every policy id to its permutation p-value, or to None where no test ran (the
    buffer was too small for a null distribution and the threshold decided for that policy, or a
    nearer policy had accepted and this one was not examined); ``calibration`` holds
    ``false_split_rate``, ``samples`` (``clustering.calibration_samples``), ``test``
    (``"pooled_permutation"``; absent in records made before the exact test), ``max_draws`` (the
    draws of a complete test), ``draws`` (``{"<id>": null draws made}``), ``fallback`` (ids
    decided by the threshold), ``accepted`` (ids that accepted ``O``, by their test or the
    threshold; never a policy that was not examined) and ``policies`` (``{"<id>": {"tested",
    "draws", "exceedances", "p_value", "decided_by", "accepted"}}``, see
    :class:`~covers_dist.clustering.bank.Calibration`).

    ``merges``: the merges the bank made just before this assignment (``{"retired", "into",
    "distance", "at_assignment", "episodes", "assignments", "time_unix"}`` each,
    :meth:`~covers_dist.clustering.bank.PolicyBank.heal`); None (and left out of :meth:`to_dict`)
    when there were none.
    """

    index: int
    policy_id: int
    decision: str
    new: bool
    distances: dict[int, float]
    threshold: float
    metric: str
    mode: str
    num_observations: int
    episode_indices: list[int]
    wall_time_ms: float
    time_unix: float
    true_groups: list[int] | None = None
    nearest_distance: float | None = field(default=None)
    p_values: dict[int, float | None] | None = None
    calibration: dict[str, Any] | None = None
    merges: list[dict[str, Any]] | None = None

    def __post_init__(self) -> None:
        if self.decision not in DECISIONS:
            raise ValueError(f"decision must be one of {list(DECISIONS)}, got {self.decision!r}")
        if self.nearest_distance is None and self.distances:
            self.nearest_distance = min(self.distances.values())

    @property
    def recalled(self) -> bool:
        """True when an existing policy was chosen (recall or recall_at_cap)."""
        return self.decision in ("recall", "recall_at_cap")

    @property
    def num_episodes(self) -> int:
        return len(self.episode_indices)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-safe dict (distance keys become strings; non-finite floats become null)."""
        d = asdict(self)
        d["distances"] = {str(k): _json_float(v) for k, v in sorted(self.distances.items())}
        d["nearest_distance"] = None if self.nearest_distance is None else _json_float(self.nearest_distance)
        d["num_episodes"] = self.num_episodes
        if self.p_values is None:
            del d["p_values"]
        else:
            d["p_values"] = {str(k): (None if v is None else float(v)) for k, v in sorted(self.p_values.items())}
        if self.calibration is None:
            del d["calibration"]
        if self.merges is None:
            del d["merges"]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "AssignmentRecord":
        """Inverse of :meth:`to_dict`."""
        data = dict(d)
        data.pop("num_episodes", None)
        data["distances"] = {int(k): (math.inf if v is None else float(v)) for k, v in data["distances"].items()}
        if data.get("nearest_distance") is None and data["distances"]:
            data["nearest_distance"] = min(data["distances"].values())
        data["episode_indices"] = [int(e) for e in data["episode_indices"]]
        if data.get("true_groups") is not None:
            data["true_groups"] = [int(g) for g in data["true_groups"]]
        if data.get("p_values") is not None:
            data["p_values"] = {int(k): (None if v is None else float(v)) for k, v in data["p_values"].items()}
        return cls(**data)
