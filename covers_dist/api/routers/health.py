"""``GET /healthz`` (the process answers) and ``GET /readyz`` (the clustering state is readable).

Both are open (no token), for load balancers and orchestrators.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from ..deps import ApiState, api_state
from ..schemas import Health, Readiness

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness: the HTTP service runs")
async def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Readiness,
    summary="Readiness: a fresh snapshot of the clustering state is available",
    responses={503: {"model": Readiness, "description": "Not ready: the clustering service has not answered."}},
)
async def readyz(state: ApiState = Depends(api_state)) -> Readiness | JSONResponse:
    cache = state.cache
    age = cache.age_s()
    stale_after = max(5 * cache.refresh_s, state.source.timeout_s + 2 * cache.refresh_s)
    if age is None:
        ready, detail = False, f"no snapshot yet: {cache.last_error or 'waiting for the first read'}"
    elif cache.last_error is not None and age > stale_after:
        ready, detail = False, f"snapshot is {age:.1f} s old; last refresh failed: {cache.last_error}"
    else:
        ready, detail = True, "ok"
    body = Readiness(ready=ready, source=state.source.kind, detail=detail, snapshot_age_s=age)
    if not ready:
        return JSONResponse(body.model_dump(), status_code=503)
    return body
