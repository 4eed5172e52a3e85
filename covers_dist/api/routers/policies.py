"""``GET /v1/policies`` and ``GET /v1/policies/{policy_id}``: the policy bank."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Path, Response

from ..deps import ERROR_RESPONSES, ApiState, api_state, current_snapshot, require_token, snapshot_json
from ..schemas import ErrorBody, Merge, PolicyList, PolicySummary, RetiredPolicy
from ..snapshot import Snapshot

router = APIRouter(prefix="/v1/policies", tags=["policies"], dependencies=[Depends(require_token)])


def _policy(entry: dict[str, Any], names: dict[str, str], model: type[PolicySummary] = PolicySummary) -> PolicySummary:
    hist = entry.get("group_histogram", {})
    by_name = {names.get(g, g): n for g, n in hist.items()}
    return model(**entry, group_histogram_by_name=by_name)


def _names(snap: Snapshot, state: ApiState) -> dict[str, str]:
    return snap.summary.get("group_names") or state.group_names


@router.get("", response_model=PolicyList, summary="Every policy in the bank", responses=ERROR_RESPONSES)
async def list_policies(
    state: ApiState = Depends(api_state), snap: Snapshot = Depends(current_snapshot)
) -> Response:
    s, names = snap.summary, _names(snap, state)

    def build() -> PolicyList:
        return PolicyList(
            current_policy_id=s.get("current_policy_id"),
            num_policies=s.get("num_policies", 0),
            policies_created=s.get("policies_created", s.get("num_policies", 0)),
            metric=s.get("metric", ""),
            threshold=s.get("threshold"),
            mode=s.get("mode", ""),
            buffer_size=s.get("buffer_size", 0),
            max_policies=s.get("max_policies", 0),
            policies=[_policy(p, names) for p in s.get("policies", [])],
            retired=[_policy(p, names, RetiredPolicy) for p in s.get("retired", [])],
            merges=[Merge(**m) for m in s.get("merges", [])],
            as_of=snap.as_of,
        )

    return snapshot_json(snap, "policies", build)


@router.get(
    "/{policy_id}",
    response_model=PolicySummary,
    summary="One policy",
    responses={**ERROR_RESPONSES, 404: {"model": ErrorBody, "description": "No policy with this id."}},
)
async def get_policy(
    policy_id: int = Path(ge=0, description="Policy id (see GET /v1/policies)."),
    state: ApiState = Depends(api_state),
    snap: Snapshot = Depends(current_snapshot),
) -> PolicySummary:
    entry = snap.policies.get(policy_id)
    if entry is None:
        raise HTTPException(404, f"policy {policy_id} does not exist; the bank holds {sorted(snap.policies)}")
    return _policy(entry, _names(snap, state))
