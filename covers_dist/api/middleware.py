"""ASGI middleware: the Host allow-list (400), the request-body cap (413), the request metrics and
the deprecation headers.

The Host allow-list answers 400 to a request whose ``Host`` header names a host the server does not
answer for: a page on another site that rebinds its own DNS name to 127.0.0.1 (DNS rebinding) then
reaches the server with its own name in ``Host``, and is refused before any route runs.

The body cap answers 413 as soon as a declared ``Content-Length`` is too large, before any of
the body is read; a body sent without a length (chunked) is read only up to the cap.
"""

from __future__ import annotations

import json
import time
from typing import Any, Awaitable, Callable

Scope = dict[str, Any]
Message = dict[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

__all__ = ["BodyLimitMiddleware", "DeprecationMiddleware", "HostAllowListMiddleware", "RequestMetricsMiddleware",
           "send_error", "host_name"]  # fmt: skip


async def send_error(send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                        *(headers or [])],
        }
    )
    await send({"type": "http.response.body", "body": body})


def host_name(header: bytes) -> str:
    """The host of a ``Host`` header (``name:port``, ``[v6]:port``), lower-cased, without the port."""
    value = header.decode("latin-1").strip().lower()
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else value
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


class HostAllowListMiddleware:
    """Answers 400 to a request whose ``Host`` header names none of ``allowed`` (lower-case names)."""

    def __init__(self, app: ASGIApp, allowed: list[str]) -> None:
        self.app = app
        self.allowed = {h.lower().rstrip(".") for h in allowed}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            hosts = [v for k, v in scope.get("headers", []) if k == b"host"]
            name = host_name(hosts[0]).rstrip(".") if hosts else None
            if name is not None and name not in self.allowed:
                shown = hosts[0][:64].decode("latin-1")
                await send_error(send, 400, f"Host header {shown!r} is not one this server answers for "
                                 f"(api.allowed_hosts: {sorted(self.allowed)})")  # fmt: skip
                return
        await self.app(scope, receive, send)


class BodyLimitMiddleware:
    """Rejects request bodies larger than ``max_bytes`` with 413 (and bad lengths with 400)."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = int(max_bytes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        too_large = f"request body larger than api.max_body_bytes={self.max_bytes}"
        close = [(b"connection", b"close")]
        declared = [v for k, v in scope.get("headers", []) if k == b"content-length"]
        if declared:
            try:
                length = int(declared[0])
                if length < 0:
                    raise ValueError
            except ValueError:
                await send_error(send, 400, f"invalid Content-Length header {declared[0][:32]!r}", close)
                return
            if length > self.max_bytes:
                await send_error(send, 413, f"{too_large} (Content-Length: {length})", close)
                return
        chunks, total, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body = message.get("body", b"")
            total += len(body)
            if total > self.max_bytes:
                await send_error(send, 413, too_large, close)
                return
            chunks.append(body)
            more = message.get("more_body", False)
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": b"".join(chunks), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class RequestMetricsMiddleware:
    """Counts requests by (method, route template, status) and times them (see routers.metrics)."""

    def __init__(self, app: ASGIApp, metrics: Any) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            self.metrics.observe(scope.get("method", ""), route, status, time.perf_counter() - t0)


class DeprecationMiddleware:
    """Marks the answers of deprecated routes (``deprecated=True``): ``Deprecation: true`` and, when
    ``successors`` maps the route's path to its replacement, ``Link: <new>; rel="successor-version"``.
    Errors of those routes (404, 422, ...) carry the headers too."""

    def __init__(self, app: ASGIApp, successors: dict[str, str] | None = None) -> None:
        self.app = app
        self.successors = dict(successors or {})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_marked(message: Message) -> None:
            route = scope.get("route")
            if message["type"] == "http.response.start" and getattr(route, "deprecated", False):
                headers = [*message.get("headers", []), (b"deprecation", b"true")]
                new = self.successors.get(getattr(route, "path", ""))
                if new:
                    headers.append((b"link", f'<{new}>; rel="successor-version"'.encode()))
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_marked)
