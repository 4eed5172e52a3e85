"""Running the HTTP service: uvicorn in a thread of this process, or in a process of its own.

:func:`start_api_server` is what a training run calls when ``api.enabled``: given the run's
config and its clustering service (the plain object in serial mode, or the named Ray actor) it
starts the service and returns a handle with ``.url`` and ``.stop()``.

* thread: uvicorn's event loop in a daemon thread (an in-process service, tests, ``serve``);
* process: ``covers-dist serve --address ... --name ...`` as a child process that joins the Ray
  cluster and reads the named clustering actor; training shares no interpreter (and no GIL)
  with it, and a failure of the service cannot take the training run down.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Protocol

import yaml

from ..config import Config, config_to_dict
from ..runtime.processes import announce
from ..runtime.run_storage import storage_location
from .sources import LocalSource, RaySource, Source

__all__ = [
    "ApiHandle", "ApiServerThread", "ApiServerProcess", "SupervisedApiServer", "start_api_server",
    "training_service", "LISTENING",
]  # fmt: skip

#: The line ``covers-dist serve`` prints once it accepts connections (followed by the URL).
LISTENING = "covers-dist serve: listening on "


class ApiHandle(Protocol):
    url: str

    def stop(self) -> None: ...


def check_exposure(app: Any, host: str) -> None:
    """Refuse to bind beyond the loopback interface an app that asks for no token: anyone who can
    reach the address could then read the run and act with its policies."""
    import ipaddress

    api = getattr(getattr(app, "state", None), "api", None)
    if api is None or getattr(api, "token", None):
        return
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        from ..config import ConfigError

        raise ConfigError(
            f"api.host={host!r} is reachable beyond this machine, and no token is set: set api.token or "
            "COVERS_API_TOKEN (clients send Authorization: Bearer <token>), or bind 127.0.0.1"
        )


class ApiServerThread:
    """uvicorn serving ``app`` from a daemon thread; ``port=0`` picks a free port."""

    def __init__(self, app: Any, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning") -> None:
        import uvicorn

        check_exposure(app, host)

        api = getattr(getattr(app, "state", None), "api", None)
        limit = getattr(getattr(api, "api", None), "max_connections", None)  # more at once: 503 at once
        config = uvicorn.Config(
            app, host=host, port=port, log_level=log_level, access_log=False, lifespan="on", limit_concurrency=limit
        )
        self.server = uvicorn.Server(config)
        self.host = host
        self.url = ""
        self._thread = threading.Thread(target=self.server.run, name="covers-api-server", daemon=True)

    def start(self, timeout_s: float = 60.0) -> "ApiServerThread":
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self.server.started:
            if not self._thread.is_alive():
                raise RuntimeError("the HTTP server stopped while starting (is the port in use?)")
            if time.monotonic() > deadline:
                self.stop()
                raise TimeoutError(f"the HTTP server did not start within {timeout_s:g} s")
            time.sleep(0.02)
        port = self.server.servers[0].sockets[0].getsockname()[1]
        host = f"[{self.host}]" if ":" in self.host else self.host
        self.url = f"http://{host}:{port}"
        return self

    @property
    def alive(self) -> bool:
        """True while the server thread runs."""
        return self._thread.is_alive()

    def stop(self, timeout_s: float = 10.0) -> None:
        self.server.should_exit = True
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def __enter__(self) -> "ApiServerThread":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


class ApiServerProcess:
    """``covers-dist serve`` in a child process (see the module docs)."""

    def __init__(self, args: list[str], cfg: Config, env: dict[str, str] | None = None) -> None:
        self._cfg_dir = tempfile.TemporaryDirectory(prefix="covers-api-")
        cfg_file = Path(self._cfg_dir.name) / "config.yaml"
        cfg_file.write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))  # holds no token
        os.chmod(cfg_file, 0o600)
        from .app import TOKEN_ENV, resolve_token

        token = resolve_token(cfg)  # handed to the child in its environment, never in a file
        env = {**(env or {}), **({TOKEN_ENV: token} if token else {})}
        self.cmd = [sys.executable, "-m", "covers_dist", "serve", *args, "--config", str(cfg_file)]
        self.url = ""
        self.output: list[str] = []
        self.proc = subprocess.Popen(
            self.cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, **(env or {})},
            start_new_session=True,
        )
        self._reader = threading.Thread(target=self._read, name="covers-api-output", daemon=True)
        self._ready = threading.Event()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            self.output = (self.output + [line])[-200:]
            if line.startswith(LISTENING) and not self._ready.is_set():
                self.url = line[len(LISTENING) :].split()[0]
                self._ready.set()
        self._ready.set()

    @property
    def alive(self) -> bool:
        """True while the child process runs."""
        return self.proc.poll() is None

    def start(self, timeout_s: float = 120.0) -> "ApiServerProcess":
        self._reader.start()
        if not self._ready.wait(timeout_s) or not self.url:
            self.stop()
            tail = "\n".join(self.output[-20:])
            raise RuntimeError(f"covers-dist serve did not start within {timeout_s:g} s; its output:\n{tail}")
        return self

    def stop(self, timeout_s: float = 15.0) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._cfg_dir.cleanup()

    def __enter__(self) -> "ApiServerProcess":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def _is_actor_handle(x: Any) -> bool:
    try:
        from ray.actor import ActorHandle
    except ImportError:  # pragma: no cover - ray is a dependency
        return False
    return isinstance(x, ActorHandle)


def start_api_server(cfg: Config, source: Any, mode: str = "auto", timeout_s: float = 120.0) -> ApiHandle:
    """Start the HTTP service on ``cfg.api.host:cfg.api.port`` for a training run.

    ``source`` is a :class:`~.sources.Source`, a plain ``ClusteringService`` (served from a
    thread of this process), or the run's clustering actor handle (served by a child process
    that joins this process's Ray cluster, unless ``mode="thread"``). Returns a handle with
    ``.url`` and ``.stop()``; the server is accepting connections when this returns.
    """
    if mode not in ("auto", "thread", "process"):
        raise ValueError(f"mode must be 'auto', 'thread' or 'process', got {mode!r}")
    actor = _is_actor_handle(source)
    if mode == "process" and not actor:
        raise ValueError("mode='process' needs the clustering actor handle (a Ray ActorHandle) as source")
    if actor and mode != "thread":
        import ray

        from ..runtime.actors import clustering_actor_name, run_namespace

        ctx = ray.get_runtime_context()
        args = ["--address", ctx.gcs_address, "--actor", clustering_actor_name(cfg), "--namespace", run_namespace(cfg)]
        args += ["--host", cfg.api.host, "--port", str(cfg.api.port)]
        return ApiServerProcess(args, cfg).start(timeout_s)
    if actor:
        src: Source = RaySource(source, cfg.api.request_timeout_s)
    elif isinstance(source, Source):
        src = source
    else:
        src = LocalSource(source, cfg.api.request_timeout_s)
    from .app import create_app

    return ApiServerThread(create_app(cfg, src), cfg.api.host, cfg.api.port).start(timeout_s)


class SupervisedApiServer:
    """The HTTP service of a training run, restarted on the same port when it dies.

    :meth:`check` (the driver calls it after every iteration) starts a new server if the old one
    stopped, on the port the first one bound (so clients keep their URL). The service's PID is
    recorded in ``processes/api.json`` of the run's storage.
    """

    def __init__(self, cfg: Config, source: Any, log: Any = print) -> None:
        self.cfg = cfg
        self.source = source
        self.log = log
        self.restarts = 0
        self.handle: Any = None

    @property
    def url(self) -> str:
        return self.handle.url if self.handle is not None else ""

    def start(self) -> "SupervisedApiServer":
        self.handle = start_api_server(self.cfg, self.source)
        if self.cfg.api.port == 0:  # keep the port it got for restarts
            port = int(self.handle.url.rsplit(":", 1)[1])
            self.cfg = dataclasses.replace(self.cfg, api=dataclasses.replace(self.cfg.api, port=port))
        proc = getattr(self.handle, "proc", None)
        announce(storage_location(self.cfg), "api", pid=proc.pid if proc is not None else os.getpid())
        return self

    def check(self) -> None:
        """Restart the service if it stopped."""
        if self.handle is None or getattr(self.handle, "alive", True):
            return
        self.log("HTTP service stopped; restarting it")
        self.handle.stop()
        self.restarts += 1
        self.start()
        self.log(f"HTTP service restarted: {self.url}")

    def stop(self) -> None:
        if self.handle is not None:
            self.handle.stop()


def training_service(cfg: Config, source: Any, log: Any = print) -> SupervisedApiServer | None:
    """The HTTP service a training run starts (``api.enabled``), supervised; None when disabled."""
    if not cfg.api.enabled:
        return None
    service = SupervisedApiServer(cfg, source, log).start()
    log(f"HTTP service: {service.url} (e.g. curl {service.url}/v1/assignments/latest; docs at {service.url}/docs)")
    return service
