"""Request and response models of the HTTP service (pydantic), one section per resource.

Observations travel as JSON in one documented shape (see docs/guide/api.md)::

    {"image": {"png_base64": "<base64 of an S x S PNG>"}          # or
              {"shape": [S, S, 3], "data": [S*S*3 integers 0..255, row-major]},
     "proprio": [P finite numbers]}

``S`` and ``P`` come from the run's observation layout (``covers_dist.envs.suite_layout``).
Floats that are not finite (an undefined ARI, a distance to an empty buffer) are sent as null.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Discriminator, Field, StrictInt, Tag

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Byte = Annotated[StrictInt, Field(ge=0, le=255)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


# ---- observations (requests) -------------------------------------------------------------------
class PngImage(_Strict):
    """An image as a base64-encoded PNG (RGB; RGBA, greyscale and palette PNGs are converted)."""

    png_base64: str = Field(description="Base64 (standard alphabet, padded) of a PNG file of S x S pixels.")


class ArrayImage(_Strict):
    """An image as a flat list of uint8 values with its shape (``image.reshape(-1).tolist()``)."""

    shape: list[StrictInt] = Field(description="[S, S, 3]: height, width, RGB channels.")
    data: list[Byte] = Field(description="S*S*3 integers in 0..255, row-major (height, width, channel).")


def _image_kind(value: Any) -> str | None:
    if isinstance(value, dict):
        return "png" if "png_base64" in value else "array"
    if isinstance(value, BaseModel):
        return "png" if isinstance(value, PngImage) else "array"
    return None


Image = Annotated[
    Annotated[PngImage, Tag("png")] | Annotated[ArrayImage, Tag("array")],
    Discriminator(
        _image_kind,
        custom_error_type="image_type",
        custom_error_message="image must be an object: {png_base64} or {shape, data}",
    ),
]


class Observation(_Strict):
    """One observation: the top-down image and the proprioceptive vector."""

    image: Image
    proprio: list[FiniteFloat] = Field(description="The P proprioceptive values (finite numbers).")


class AssignRequest(_Strict):
    """A what-if assignment query: the first frames of one or more episodes."""

    observations: list[Observation] = Field(
        min_length=1, description="Initial observations (a multiple of clustering.initial_frames of them)."
    )


class ActRequest(_Strict):
    """One observation to act on, with an optional policy id (default: the current policy)."""

    observation: Observation
    policy_id: Annotated[StrictInt, Field(ge=0)] | None = Field(
        default=None, description="Policy to run; null or absent: the bank's current policy."
    )
    deterministic: bool = Field(default=True, description="Return the Gaussian's mean (true) or a sample (false).")


# ---- policies ----------------------------------------------------------------------------------
class PolicySummary(BaseModel):
    """One policy of the bank."""

    policy_id: int
    created_at_episode: int = Field(description="Index of the first episode assigned to it.")
    created_at_assignment: int = Field(description="Index of the assignment that created it.")
    created_at_time: float | None = Field(description="Unix time of its creation.")
    episodes_assigned: int
    assignments: int = Field(description="Assignment steps that chose this policy.")
    buffer_size: int = Field(description="Initial observations held in its buffer B_i.")
    buffer_capacity: int
    frames_seen: int = Field(description="Initial observations ever offered to its buffer.")
    group_histogram: dict[str, int] = Field(
        description="Episodes per true task group id (from the stream's labels; for evaluation only)."
    )
    group_histogram_by_name: dict[str, int] = Field(description="The same histogram keyed by base task name.")
    episodes_reported: int = Field(description="Finished episodes whose statistics were reported.")
    last_success: float | None = Field(description="Success of its latest reported episode.")
    last_return: float | None = Field(description="Return of its latest reported episode.")


class Merge(BaseModel):
    """One repaired split: a policy retired into an older one (docs/guide/clustering.md, "A bank that heals")."""

    retired: int = Field(description="The policy merged away: never chosen again, its id never reused.")
    into: int = Field(description="The policy that took its frames, episodes and labels.")
    distance: float | None = Field(description="W1 between the two buffers when they were merged.")
    at_assignment: int = Field(description="Assignments made before the merge.")
    episodes: int = Field(description="Episodes the retired policy had been assigned.")
    assignments: int
    time_unix: float | None


class RetiredPolicy(PolicySummary):
    """A policy merged into another."""

    merged_into: int


class PolicyList(BaseModel):
    """Every policy of the bank and the bank's settings."""

    current_policy_id: int | None
    num_policies: int
    policies_created: int = Field(0, description="Policies ever created: num_policies plus the retired ones.")
    metric: str
    threshold: float | None
    mode: str
    buffer_size: int
    max_policies: int
    policies: list[PolicySummary]
    retired: list[RetiredPolicy] = Field(default_factory=list, description="Policies merged into another.")
    merges: list[Merge] = Field(default_factory=list, description="Every merge, in order.")
    as_of: float = Field(description="Unix time at which this state was read from the clustering service.")


# ---- assignments -------------------------------------------------------------------------------
class AssignmentRecord(BaseModel):
    """One assignment decision, as the bank recorded it."""

    index: int = Field(description="Position in the assignment history (0-based).")
    policy_id: int
    decision: Literal["adopt", "new", "recall", "recall_at_cap"]
    new: bool = Field(description="True when the assignment created the policy (adopt or new).")
    distances: dict[str, float | None] = Field(description="Distance to every policy present before it (by id).")
    nearest_distance: float | None
    threshold: float | None
    metric: str
    mode: str
    num_observations: int
    num_episodes: int
    episode_indices: list[int]
    true_groups: list[int] | None = Field(description="True group id of each episode (evaluation only).")
    wall_time_ms: float | None
    time_unix: float | None = Field(description="Unix time of the decision.")
    merges: list[Merge] | None = Field(None, description="Merges the bank made just before this assignment.")


class CurrentAssignment(BaseModel):
    """The current policy and the latest assignment record."""

    current_policy_id: int | None
    num_assignments: int
    last: AssignmentRecord | None
    as_of: float


class AssignmentPage(BaseModel):
    """A page of the assignment history."""

    total: int = Field(description="Assignments recorded so far.")
    since: int
    limit: int
    next_since: int | None = Field(description="``since`` of the next page, null when this page reaches the end.")
    items: list[AssignmentRecord]
    as_of: float


class WhatIfResult(BaseModel):
    """What the bank would decide for the posted observations (nothing is changed)."""

    policy_id: int = Field(description="The policy that would be chosen (a fresh id when ``new``).")
    decision: Literal["adopt", "new", "recall", "recall_at_cap"]
    new: bool
    distances: dict[str, float | None]
    nearest_distance: float | None
    threshold: float | None
    metric: str
    mode: str
    num_observations: int
    wall_time_ms: float | None


# ---- acting ------------------------------------------------------------------------------------
class ActResult(BaseModel):
    """The action of a policy for one observation."""

    policy_id: int
    action: list[float | None]
    value: float | None = Field(description="The critic's value estimate.")
    deterministic: bool


# ---- metrics and health ------------------------------------------------------------------------
class TrainingMetrics(BaseModel):
    """Training progress and clustering quality."""

    iteration: int | None
    episodes: int | None
    env_steps: int | None
    env_steps_per_s: float | None
    ari: float | None = Field(description="Adjusted Rand Index between policy ids and true groups (null: no data).")
    episodes_labelled: int | None
    num_policies: int
    current_policy_id: int | None
    success: dict[str, float | None] = Field(
        description="Latest success rate per base task (from the latest metrics row that had the task)."
    )
    returns: dict[str, float | None] = Field(description="Latest average return per base task (likewise).")
    policy_counts: dict[str, int] = Field(description="Labelled episodes per policy id.")
    confusion: dict[str, Any] = Field(description="policies x groups episode counts.")
    progress: dict[str, float | int | str | bool | None] = Field(description="The driver's latest metrics row.")
    evaluation: dict[str, float | int | None] = Field(
        default_factory=dict,
        description="Continual-learning metrics of the latest evaluation pass (eval/average_success, "
        "eval/zero_shot_success, eval/average_forgetting, eval/success/<task>, eval/forgetting/<task>, ...; "
        "docs/RESULTS.md); empty when the run does not evaluate.",
    )
    as_of: float


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    ready: bool
    source: str = Field(description="Where the data comes from: 'ray' (a running cluster) or 'local'.")
    detail: str
    snapshot_age_s: float | None


class ErrorBody(BaseModel):
    """Every error answer: a human-readable message (and, for validation errors, the first problems)."""

    detail: str
    errors: list[dict[str, Any]] | None = None
