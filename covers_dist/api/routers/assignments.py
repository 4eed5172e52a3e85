"""Assignments: ``GET /v1/assignments/latest`` (the current policy and the latest record),
``GET /v1/assignments`` (the history, paged) and ``POST /v1/assignments/what-if`` (what the bank
would decide for posted observations, changing nothing).

``GET /v1/assignment`` and ``POST /v1/assign``, the old names of the first and the last, stay for
one release: marked deprecated in the schema, answered with ``Deprecation: true`` and a ``Link`` to
the new path (:data:`SUCCESSORS`, added by the app's middleware)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Query, Response

from ..deps import ERROR_RESPONSES, ApiState, api_state, call_on_observations, current_snapshot, require_token
from ..deps import snapshot_json
from ..schemas import AssignmentPage, AssignmentRecord, AssignRequest, CurrentAssignment, ErrorBody, WhatIfResult
from ..snapshot import Snapshot, json_safe

router = APIRouter(prefix="/v1", tags=["assignments"], dependencies=[Depends(require_token)])

MAX_PAGE = 1000
LATEST, WHAT_IF = "/v1/assignments/latest", "/v1/assignments/what-if"
#: Deprecated paths and the paths that replace them (removed in the release after 0.1).
SUCCESSORS: dict[str, str] = {"/v1/assignment": LATEST, "/v1/assign": WHAT_IF}


def _deprecated(new: str) -> str:
    return f"Deprecated alias of `{new}` (same answer), removed in the next release."


@router.get(
    "/assignments/latest",
    response_model=CurrentAssignment,
    summary="The current policy and the latest assignment record",
    responses=ERROR_RESPONSES,
)
async def latest_assignment(snap: Snapshot = Depends(current_snapshot)) -> Response:
    def build() -> CurrentAssignment:
        return CurrentAssignment(
            current_policy_id=snap.summary.get("current_policy_id"),
            num_assignments=len(snap.history),
            last=AssignmentRecord(**snap.last) if snap.last else None,
            as_of=snap.as_of,
        )

    return snapshot_json(snap, "assignment", build)


@router.get(
    "/assignment",
    response_model=CurrentAssignment,
    summary="The current policy and the latest assignment record (deprecated path)",
    description=_deprecated(f"GET {LATEST}"),
    responses=ERROR_RESPONSES,
    deprecated=True,
)
async def current_assignment(snap: Snapshot = Depends(current_snapshot)) -> Response:
    return await latest_assignment(snap)


@router.get(
    "/assignments",
    response_model=AssignmentPage,
    summary="The assignment history, oldest first, paged",
    responses=ERROR_RESPONSES,
)
async def assignment_history(
    since: int = Query(0, ge=0, description="Index of the first record to return."),
    limit: int = Query(100, ge=1, le=MAX_PAGE, description=f"Records per page (1..{MAX_PAGE})."),
    snap: Snapshot = Depends(current_snapshot),
) -> AssignmentPage:
    total = len(snap.history)
    items = snap.history[since : since + limit]
    end = since + len(items)
    return AssignmentPage(
        total=total,
        since=since,
        limit=limit,
        next_since=end if end < total else None,
        items=[AssignmentRecord(**r) for r in items],
        as_of=snap.as_of,
    )


WHAT_IF_RESPONSES = {**ERROR_RESPONSES, 409: {"model": ErrorBody, "description": "The policy bank is still empty."}}


@router.post(
    "/assignments/what-if",
    response_model=WhatIfResult,
    summary="What-if: the policy the bank would assign to these initial observations",
    description=(
        "Computes the distances from the posted observations (the first frames of one or more "
        "episodes) to every policy's buffer and applies the assignment rule, without changing "
        "the bank."
    ),
    responses=WHAT_IF_RESPONSES,
)
async def what_if(body: AssignRequest, state: ApiState = Depends(api_state)) -> WhatIfResult:
    n = len(body.observations)
    if n > state.api.max_batch:
        raise HTTPException(422, f"observations: {n} given, at most api.max_batch={state.api.max_batch} allowed")
    if n % state.initial_frames:
        raise HTTPException(
            422, f"observations: {n} given, not a multiple of clustering.initial_frames={state.initial_frames}"
        )
    record = await call_on_observations(state, body.observations, "what_if")
    fields = WhatIfResult.model_fields
    return WhatIfResult(**{k: v for k, v in json_safe(record).items() if k in fields})


@router.post(
    "/assign",
    response_model=WhatIfResult,
    summary="What-if: the policy the bank would assign to these initial observations (deprecated path)",
    description=_deprecated(f"POST {WHAT_IF}"),
    responses=WHAT_IF_RESPONSES,
    deprecated=True,
)
async def what_if_deprecated(body: AssignRequest, state: ApiState = Depends(api_state)) -> WhatIfResult:
    return await what_if(body, state)
