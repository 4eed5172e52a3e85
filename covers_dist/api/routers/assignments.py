"""Assignments: ``GET /v1/assignment`` (current), ``GET /v1/assignments`` (history, paged) and
``POST /v1/assign`` (what the bank would decide for posted observations, changing nothing)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Query, Response

from ..deps import ERROR_RESPONSES, ApiState, api_state, call_source, current_snapshot, require_token, snapshot_json
from ..observations import ObservationError, decode_observations
from ..schemas import AssignmentPage, AssignmentRecord, AssignRequest, CurrentAssignment, ErrorBody, WhatIfResult
from ..snapshot import Snapshot, json_safe

router = APIRouter(prefix="/v1", tags=["assignments"], dependencies=[Depends(require_token)])

MAX_PAGE = 1000


@router.get(
    "/assignment",
    response_model=CurrentAssignment,
    summary="The current policy and the latest assignment record",
    responses=ERROR_RESPONSES,
)
async def current_assignment(snap: Snapshot = Depends(current_snapshot)) -> Response:
    def build() -> CurrentAssignment:
        return CurrentAssignment(
            current_policy_id=snap.summary.get("current_policy_id"),
            num_assignments=len(snap.history),
            last=AssignmentRecord(**snap.last) if snap.last else None,
            as_of=snap.as_of,
        )

    return snapshot_json(snap, "assignment", build)


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


@router.post(
    "/assign",
    response_model=WhatIfResult,
    summary="What-if: the policy the bank would assign to these initial observations",
    description=(
        "Computes the distances from the posted observations (the first frames of one or more "
        "episodes) to every policy's buffer and applies the assignment rule, without changing "
        "the bank."
    ),
    responses={**ERROR_RESPONSES, 409: {"model": ErrorBody, "description": "The policy bank is still empty."}},
)
async def what_if(body: AssignRequest, state: ApiState = Depends(api_state)) -> WhatIfResult:
    n = len(body.observations)
    if n > state.api.max_batch:
        raise HTTPException(422, f"observations: {n} given, at most api.max_batch={state.api.max_batch} allowed")
    if n % state.initial_frames:
        raise HTTPException(
            422, f"observations: {n} given, not a multiple of clustering.initial_frames={state.initial_frames}"
        )
    try:
        obs = decode_observations(body.observations, state.layout)
    except ObservationError as e:
        raise HTTPException(422, str(e)) from None
    record = await call_source(state, "what_if", obs)
    fields = WhatIfResult.model_fields
    return WhatIfResult(**{k: v for k, v in json_safe(record).items() if k in fields})
