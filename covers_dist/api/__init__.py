"""The HTTP service (FastAPI + uvicorn): policy ids, cluster assignments and metrics of a run.

* :func:`create_app` builds the app for a :class:`Source` (a clustering service in this
  process, or the named clustering actor of a Ray job);
* :func:`start_api_server` starts it next to a training run (a thread, or a process of its own);
* ``covers-dist serve`` runs it standalone against a cluster or a saved run.

See docs/guide/api.md for the endpoints and the JSON shape of observations.
"""

from .app import TOKEN_ENV, create_app, resolve_token
from .observations import ObservationError, decode_observations, encode_png, observation_json
from .server import ApiServerProcess, ApiServerThread, SupervisedApiServer, start_api_server, training_service
from .sources import LocalSource, RaySource, Source, SourceUnavailable, load_checkpoint_source

__all__ = [
    "TOKEN_ENV",
    "ApiServerProcess",
    "ApiServerThread",
    "LocalSource",
    "ObservationError",
    "RaySource",
    "Source",
    "SourceUnavailable",
    "create_app",
    "decode_observations",
    "encode_png",
    "load_checkpoint_source",
    "observation_json",
    "resolve_token",
    "start_api_server",
    "SupervisedApiServer",
    "training_service",
]
