"""Where the HTTP service reads from: a clustering service in this process, or the Ray actor.

A :class:`Source` forwards calls by method name to a
:class:`~covers_dist.runtime.clustering_service.ClusteringService` and raises the service's own
errors (``KeyError`` unknown policy, ``LookupError`` empty bank, ``ValueError``/``TypeError`` bad
input); a service that cannot be reached or does not answer in time raises
:class:`SourceUnavailable`. Calls block: the app runs them in a thread pool.

* :class:`LocalSource`: a service object in this process (serial training, or a saved run
  loaded read-only with :func:`load_checkpoint_source`).
* :class:`RaySource`: the named clustering actor of a running training job
  (``covers-clustering-<run name>``), found with :meth:`RaySource.connect`.
"""

from __future__ import annotations

import os
import threading
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

__all__ = [
    "Source",
    "LocalSource",
    "RaySource",
    "SourceUnavailable",
    "load_checkpoint_source",
    "connect_ray",
    "SERVICE_ERRORS",
]

#: Errors raised by the clustering service for a bad query; passed on to the caller unchanged.
SERVICE_ERRORS = (KeyError, LookupError, ValueError, TypeError, PermissionError)


class SourceUnavailable(RuntimeError):
    """The clustering service cannot be reached, failed, or did not answer in time."""


class Source(ABC):
    """Calls into a clustering service by method name (blocking)."""

    kind: str = "source"

    def __init__(self, timeout_s: float = 30.0) -> None:
        self.timeout_s = float(timeout_s)

    @abstractmethod
    def call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        """``service.<method>(*args, **kwargs)``; the service's errors pass through."""

    def call_many(self, methods: list[str]) -> list[Any]:
        """Several argument-free calls (a remote source sends them together)."""
        return [self.call(m) for m in methods]

    def close(self) -> None:
        """Release what the source holds (nothing by default)."""


class LocalSource(Source):
    """A :class:`~covers_dist.runtime.clustering_service.ClusteringService` in this process."""

    kind = "local"

    def __init__(self, service: Any, timeout_s: float = 30.0) -> None:
        super().__init__(timeout_s)
        self.service = service

    def call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        return getattr(self.service, method)(*args, **kwargs)


class RaySource(Source):
    """The named clustering actor of a Ray job (calls are ``ray.get(actor.method.remote(...))``)."""

    kind = "ray"

    def __init__(self, actor: Any, timeout_s: float = 30.0) -> None:
        super().__init__(timeout_s)
        self.actor = actor

    def _get(self, refs: Any) -> Any:
        import ray
        from ray import exceptions as rex

        try:
            return ray.get(refs, timeout=self.timeout_s)
        except rex.GetTimeoutError:
            raise SourceUnavailable(f"the clustering actor did not answer within {self.timeout_s:g} s") from None
        except rex.RayTaskError as e:
            cause = getattr(e, "cause", None)
            if isinstance(cause, SERVICE_ERRORS):
                raise cause from None
            raise SourceUnavailable(f"the clustering actor failed: {type(cause or e).__name__}: {cause or e}") from None
        except (rex.RayActorError, rex.RaySystemError, rex.ObjectLostError) as e:
            raise SourceUnavailable(f"the clustering actor is unavailable: {type(e).__name__}") from None

    def call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        return self._get(getattr(self.actor, method).remote(*args, **kwargs))

    def call_many(self, methods: list[str]) -> list[Any]:
        return self._get([getattr(self.actor, m).remote() for m in methods])

    @classmethod
    def connect(
        cls, name: str, namespace: str | None = None, address: str | None = None, timeout_s: float = 30.0
    ) -> "RaySource":
        """Find the clustering actor ``name`` (connecting to Ray at ``address`` first if needed).

        With no ``namespace`` the actor is looked up in this job's namespace, then in every
        namespace of the cluster (an error lists the candidates when the name is ambiguous).
        """
        return cls(find_actor(name, namespace, address), timeout_s)


_RAY_LOCK = threading.Lock()


def _check_reachable(address: str | None, timeout_s: float = 5.0) -> None:
    """Fail fast (ray.init retries for minutes) when a ``host:port`` address does not answer."""
    import socket

    if not address or address == "auto" or "://" in address or ":" not in address:
        return
    host, _, port = address.rpartition(":")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            pass
    except (OSError, ValueError) as e:
        raise SourceUnavailable(f"no Ray cluster answers at {address} ({e})") from None


def connect_ray(address: str | None) -> Any:
    """Join the Ray cluster at ``address`` (this process's Ray if already connected)."""
    import ray

    with _RAY_LOCK:
        if ray.is_initialized():
            current = ray.get_runtime_context().gcs_address
            same = address and address.replace("localhost:", "127.0.0.1:") == current
            if address and address != "auto" and "://" not in address and not same:
                _check_reachable(address)  # an address that does not answer says so, connected or not
                raise SourceUnavailable(
                    f"this process is connected to the Ray cluster at {current}; it cannot also join {address}"
                )
            return ray
        _check_reachable(address)
        if address and address.split(":")[0] in ("127.0.0.1", "localhost"):
            # a loopback-only cluster: this process must advertise 127.0.0.1 too
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
            if os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] == "0":
                from ray._private import ray_constants

                ray_constants.ENABLE_RAY_CLUSTER = False
        ray.init(address=address, log_to_driver=False, configure_logging=True, logging_level="WARNING")
        return ray


def find_actor(name: str, namespace: str | None = None, address: str | None = None) -> Any:
    """The named actor ``name`` of the Ray cluster (see :meth:`RaySource.connect`)."""
    ray = connect_ray(address)
    try:
        return ray.get_actor(name, namespace=namespace)
    except ValueError:
        if namespace is not None:
            raise SourceUnavailable(f"no Ray actor named {name!r} in namespace {namespace!r}") from None
    from ray.util import list_named_actors

    matches = sorted({a["namespace"] for a in list_named_actors(all_namespaces=True) if a["name"] == name})
    if not matches:
        raise SourceUnavailable(f"no Ray actor named {name!r} in any namespace of this cluster (is training running?)")
    if len(matches) > 1:
        raise SourceUnavailable(f"Ray actor {name!r} exists in several namespaces {matches}: pass --namespace")
    return ray.get_actor(name, namespace=matches[0])


# ---- a saved run, read-only ------------------------------------------------------------------------
def load_checkpoint_source(run_dir: str | Path, timeout_s: float = 30.0) -> tuple[LocalSource, Any, Path]:
    """A read-only clustering service over the newest valid checkpoint of ``run_dir``.

    Returns ``(source, run config, checkpoint path)``. The bank comes from ``<ckpt>/bank`` and
    each policy's weights from ``<ckpt>/learners/policy-N.pt``.
    """
    from ..runtime.saved_run import load_saved_run

    run = load_saved_run(run_dir)
    return LocalSource(run.service, timeout_s), run.cfg, run.checkpoint
