"""The FastAPI app factory: one router per resource, shared state opened in the lifespan.

``create_app(cfg, source)`` serves the clustering service behind ``source`` (see
:mod:`.sources`) with the settings of ``cfg.api``; the run's observation layout
(``cfg.env.suite``, ``cfg.env.image_size``) decides which posted observations are valid.
Interactive docs are at ``/docs``, the schema at ``/openapi.json`` (both open, like the health
checks); everything else needs ``Authorization: Bearer <token>`` when a token is configured.
"""

from __future__ import annotations

import asyncio
import logging
import os
from contextlib import asynccontextmanager
from typing import Any, AsyncIterator

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from .. import __version__
from ..config import Config
from ..envs import suite_layout
from .deps import ApiState
from .middleware import BodyLimitMiddleware, DeprecationMiddleware, HostAllowListMiddleware, RequestMetricsMiddleware
from .routers import actions, assignments, health, metrics, policies
from .snapshot import SnapshotCache
from .sources import Source

__all__ = ["create_app", "resolve_token", "allowed_hosts", "TOKEN_ENV", "LOOPBACK_NAMES"]

log = logging.getLogger("covers_dist.api")

#: Environment variable read for the bearer token when ``api.token`` is not set.
TOKEN_ENV = "COVERS_API_TOKEN"
MAX_REPORTED_ERRORS = 10


def resolve_token(cfg: Config) -> str | None:
    """``api.token``, else the first line of ``api.token_file``, else ``$COVERS_API_TOKEN``, else
    None (no auth); empty strings mean none. A token file that cannot be read, or holds no token,
    raises :class:`~covers_dist.config.ConfigError` naming it (never its content)."""
    from ..config import ConfigError

    if cfg.api.token:
        return cfg.api.token
    if cfg.api.token_file:
        try:
            lines = open(cfg.api.token_file, encoding="utf-8").read().splitlines()  # noqa: SIM115
        except (OSError, UnicodeDecodeError) as e:
            raise ConfigError(f"api.token_file={cfg.api.token_file!r} cannot be read ({type(e).__name__})") from None
        token = lines[0].strip() if lines else ""
        if not token:
            raise ConfigError(f"api.token_file={cfg.api.token_file!r} holds no token (its first line is empty)")
        return token
    return os.environ.get(TOKEN_ENV) or None


#: Host names a server with no token answers for by default (api.allowed_hosts: null).
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def allowed_hosts(cfg: Config, token: str | None) -> list[str] | None:
    """The ``Host`` names the server answers for, or None for any: ``api.allowed_hosts`` when set
    (``['*']``: any); else, with no token, the loopback names and ``api.host`` (unless it is a
    wildcard address); with a token, any (a page that rebinds its DNS name has no token to send)."""
    given = cfg.api.allowed_hosts
    if given is not None:
        return None if "*" in given else list(given)
    if token:
        return None
    extra = [] if cfg.api.host in ("0.0.0.0", "::") else [cfg.api.host]
    return [*LOOPBACK_NAMES, *extra]


def _location(loc: Any) -> str:
    parts = [str(p) for p in loc if p not in ("body",)] if isinstance(loc, (list, tuple)) else [str(loc)]
    return ".".join(parts) or "body"


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    errors = [
        {"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
        for e in exc.errors()[:MAX_REPORTED_ERRORS]
    ]
    first = exc.errors()[0] if exc.errors() else {}
    more = len(exc.errors()) - 1
    msg = first.get("msg", "invalid")
    loc = tuple(first.get("loc", ()))
    if loc == ("body",) and first.get("type") in ("model_attributes_type", "dict_type"):
        msg = "the body must be a JSON object (Content-Type: application/json)"
    if first.get("type") == "json_invalid":
        why = (first.get("ctx") or {}).get("error", "")
        at = f" at character {loc[1]}" if len(loc) > 1 else ""
        detail = f"invalid request: the body is not valid JSON{at}" + (f" ({why})" if why else "")
    else:
        detail = f"invalid request: {_location(loc)}: {msg}"
    if more > 0:
        detail += f" (and {more} more problem{'s' if more > 1 else ''})"
    return JSONResponse({"detail": detail, "errors": errors}, status_code=422)


async def _http_error(request: Request, exc: StarletteHTTPException) -> Any:
    if exc.status_code == 400 and exc.detail == "There was an error parsing the body":
        exc = StarletteHTTPException(400, "the body could not be parsed: send UTF-8 encoded JSON", exc.headers)
    return await http_exception_handler(request, exc)


def create_app(cfg: Config, source: Source, *, token: str | None = None) -> FastAPI:
    """The HTTP service for ``source``.

    ``token`` overrides :func:`resolve_token` when given (an empty string turns auth off).
    """
    layout = suite_layout(cfg.env.suite, cfg.env.image_size)
    cache = SnapshotCache(source, cfg.api.refresh_s)
    state = ApiState(
        source=source,
        cache=cache,
        layout=layout,
        api=cfg.api,
        token=(token if token is not None else resolve_token(cfg)) or None,
        initial_frames=cfg.clustering.initial_frames,
        group_names={str(i): t for i, t in enumerate(cfg.env.tasks)},
    )
    registry, request_metrics = metrics.make_registry(cache)
    state.prometheus, state.request_metrics = registry, request_metrics

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state.compute = asyncio.Semaphore(cfg.api.compute_concurrency)
        await asyncio.get_running_loop().run_in_executor(None, cache.start)
        try:
            yield
        finally:
            await asyncio.get_running_loop().run_in_executor(None, cache.stop)

    app = FastAPI(
        title="covers-dist",
        version=__version__,
        summary="Policy ids, cluster assignments and training metrics of a COVERS run.",
        lifespan=lifespan,
    )
    app.state.api = state
    app.add_exception_handler(RequestValidationError, _validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, _http_error)  # type: ignore[arg-type]
    for router in (health.router, policies.router, assignments.router, actions.router, metrics.router):
        app.include_router(router)
    app.add_middleware(DeprecationMiddleware, successors=assignments.SUCCESSORS)
    app.add_middleware(BodyLimitMiddleware, max_bytes=cfg.api.max_body_bytes)
    allowed = allowed_hosts(cfg, state.token)
    if allowed is not None:
        app.add_middleware(HostAllowListMiddleware, allowed=allowed)
    app.add_middleware(RequestMetricsMiddleware, metrics=request_metrics)  # outermost: counts 413s too
    return app
