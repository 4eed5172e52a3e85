"""What the routers share: the app's state, the auth check, and calls into the source.

Blocking calls (a Ray round trip, a forward pass) run in the thread pool, so the event loop
never waits on them; the service's errors become 4xx answers with its message, an unreachable
service 503.
"""

from __future__ import annotations

import asyncio
import secrets
from dataclasses import dataclass, field
from typing import Any, Callable

from fastapi import Depends, HTTPException, Request, Response
from pydantic import BaseModel
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool

from ..config import ApiConfig
from ..envs.layout import ObsLayout
from .observations import ObservationError, decode_observations
from .snapshot import Snapshot, SnapshotCache
from .sources import Source, SourceUnavailable

__all__ = [
    "ApiState",
    "api_state",
    "require_token",
    "call_on_observations",
    "current_snapshot",
    "call_source",
    "snapshot_json",
    "ERROR_RESPONSES",
]

_bearer = HTTPBearer(auto_error=False, description="Bearer token (api.token or COVERS_API_TOKEN), when set.")


@dataclass
class ApiState:
    """Everything a request handler needs, created once per app."""

    source: Source
    cache: SnapshotCache
    layout: ObsLayout
    api: ApiConfig
    token: str | None
    initial_frames: int
    group_names: dict[str, str] = field(default_factory=dict)
    compute: asyncio.Semaphore | None = None  # made in the app's lifespan (bound to its event loop)
    prometheus: Any = None  # the app's prometheus_client CollectorRegistry
    request_metrics: Any = None


# Dependencies are coroutines: FastAPI runs plain-function dependencies in the thread pool, which
# costs more than everything else a cached GET answer does.
async def api_state(request: Request) -> ApiState:
    return request.app.state.api


async def require_token(
    state: ApiState = Depends(api_state),
    creds: HTTPAuthorizationCredentials | None = Depends(_bearer),
) -> None:
    """401 unless the request carries ``Authorization: Bearer <token>`` (when a token is set)."""
    if state.token is None:
        return
    if creds is None or not secrets.compare_digest(creds.credentials.encode(), state.token.encode()):
        raise HTTPException(401, "missing or invalid bearer token", headers={"WWW-Authenticate": "Bearer"})


async def current_snapshot(state: ApiState = Depends(api_state)) -> Snapshot:
    """The latest snapshot, or 503 when none could be read yet."""
    snap = state.cache.latest
    if snap is None:
        why = state.cache.last_error or "no snapshot read yet"
        raise HTTPException(503, f"the clustering service has not answered yet ({why})")
    return snap


def snapshot_json(snap: Snapshot, key: str, build: Callable[[], BaseModel]) -> Response:
    """The JSON answer ``build()`` for ``snap``, serialized once per snapshot and then reused."""
    body = snap.rendered.get(key)
    if body is None:
        body = snap.rendered[key] = build().model_dump_json().encode()
    return Response(body, media_type="application/json")


def _describe_key_error(e: KeyError) -> str:
    key = e.args[0] if e.args else None
    if key is None:
        return "the bank has no current policy yet"
    return f"policy {key} is unknown or has no weights loaded"


async def call_source(state: ApiState, method: str, *args: Any, **kwargs: Any) -> Any:
    """``source.<method>(...)`` in the thread pool (at most ``api.compute_concurrency`` at once)."""
    assert state.compute is not None
    async with state.compute:
        return await _call(state, method, *args, **kwargs)


async def call_on_observations(state: ApiState, observations: Any, method: str, *args: Any) -> Any:
    """``source.<method>(decoded, *args)`` for JSON ``observations``: the PNG decoding and the call
    both run in the thread pool, never on the event loop, in one of the ``api.compute_concurrency``
    slots; an observation that does not decode is a 422 naming it."""
    assert state.compute is not None
    async with state.compute:
        try:
            obs = await run_in_threadpool(decode_observations, observations, state.layout)
        except ObservationError as e:
            raise HTTPException(422, str(e)) from None
        return await _call(state, method, obs, *args)


async def _call(state: ApiState, method: str, *args: Any, **kwargs: Any) -> Any:
    try:
        return await run_in_threadpool(state.source.call, method, *args, **kwargs)
    except SourceUnavailable as e:
        raise HTTPException(503, str(e)) from None
    except KeyError as e:  # before LookupError: KeyError is one
        raise HTTPException(404, _describe_key_error(e)) from None
    except LookupError as e:
        raise HTTPException(409, str(e)) from None
    except PermissionError as e:
        raise HTTPException(403, str(e)) from None
    except (ObservationError, ValueError, TypeError) as e:
        raise HTTPException(422, str(e)) from None


def _err(description: str) -> dict[str, Any]:
    from .schemas import ErrorBody

    return {"model": ErrorBody, "description": description}


#: Error answers documented on the protected routes (OpenAPI ``responses``).
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    400: _err("The request could not be read (e.g. a body that is not UTF-8, a bad Content-Length)."),
    401: _err("Missing or invalid bearer token."),
    413: _err("Request body larger than api.max_body_bytes."),
    422: _err("Malformed request: the message names the field and the problem."),
    503: _err("The clustering service is unreachable or has not answered yet."),
}
