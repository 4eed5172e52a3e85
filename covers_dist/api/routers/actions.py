"""``POST /v1/act``: the action of a policy (default: the current one) for one observation."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from ..deps import ERROR_RESPONSES, ApiState, api_state, call_on_observations, require_token
from ..schemas import ActRequest, ActResult, ErrorBody
from ..snapshot import json_safe

router = APIRouter(prefix="/v1", tags=["actions"], dependencies=[Depends(require_token)])


@router.post(
    "/act",
    response_model=ActResult,
    summary="The action of a policy for one observation",
    description="Deterministic (the Gaussian's mean) unless `deterministic` is false.",
    responses={**ERROR_RESPONSES, 404: {"model": ErrorBody, "description": "Unknown policy, or no policy yet."}},
)
async def act(body: ActRequest, state: ApiState = Depends(api_state)) -> ActResult:
    out = await call_on_observations(state, [body.observation], "act", body.policy_id, body.deterministic)
    out = json_safe(out)
    return ActResult(
        policy_id=int(out["policy_id"]),
        action=list(out["action"][0]),
        value=out["value"][0],
        deterministic=body.deterministic,
    )
