"""Starting or joining Ray, loopback-only by default.

A local Ray instance binds to the machine's network address unless
``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` is set before Ray starts; with it, every Ray process
binds and talks on 127.0.0.1 only. :func:`init_ray` sets it (unless the caller set it
otherwise), gives the run its own temp dir (removed by :func:`shutdown_ray`, Ray's logs with it,
unless the caller keeps them), and never stops anything it did not start.

Ray puts the driver's current directory at the front of its workers' ``sys.path``. Started from a
directory that holds another copy of the package (a second checkout, an older clone), the workers
would import that copy while the driver runs the installed one: every env and learner would run
other code than the command was given, silently. :func:`init_ray` checks it on the instances it
starts (:func:`check_workers_import_this_package`) and refuses such a start with an error that
names both copies.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from typing import Any

__all__ = ["init_ray", "check_workers_import_this_package", "loopback_only", "ray_temp_dir", "shutdown_ray", "failing", "resolve_weights", "check_run_dir_outlives_the_job"]

_STARTED_HERE = False
_TEMP_DIR: str | None = None  # the temp dir of the instance started here


def init_ray(num_cpus: int, address: str | None = None, num_gpus: float | None = None) -> Any:
    """Connect to ``address`` or start a local, loopback-only Ray instance with ``num_cpus``."""
    global _STARTED_HERE, _TEMP_DIR
    import ray

    if ray.is_initialized():
        return ray
    if address is None:
        address = os.environ.get("RAY_ADDRESS") or None
    if address:
        ray.init(address=address, log_to_driver=True)
        return ray
    # only for an instance we start ourselves: a cluster's nodes must advertise their real address
    loopback_only()
    tmp = _TEMP_DIR = ray_temp_dir()
    ray.init(
        num_cpus=num_cpus,
        num_gpus=num_gpus,
        include_dashboard=False,
        _temp_dir=tmp,
        _node_ip_address="127.0.0.1",
        configure_logging=True,
        logging_level="WARNING",
    )
    _STARTED_HERE = True
    try:
        check_workers_import_this_package(ray)
    except BaseException:
        shutdown_ray(keep_logs=False)
        raise
    return ray


def _package_fingerprint() -> tuple[str, str]:
    """(the directory ``covers_dist`` is imported from, a hash of its Python sources). Run in the
    driver and, as a copy pickled by value, in a worker: it imports what it needs itself, so it
    runs with whatever copy of the package the worker finds."""
    import hashlib
    import os as _os

    import covers_dist

    root = _os.path.dirname(_os.path.abspath(covers_dist.__file__))
    digest = hashlib.sha256()
    for base, dirs, files in _os.walk(root):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(f for f in files if f.endswith(".py")):
            path = _os.path.join(base, name)
            digest.update(_os.path.relpath(path, root).encode())
            with open(path, "rb") as fh:
                digest.update(fh.read())
    return root, digest.hexdigest()


def check_workers_import_this_package(ray: Any) -> None:
    """Raise if a Ray worker imports a ``covers_dist`` whose sources differ from the driver's (Ray
    puts the driver's working directory first on its workers' ``sys.path``, so a copy of the
    package there wins over the installed one). The same sources in another place (an installed
    copy of the checkout the command runs in) pass."""

    import builtins
    import types

    # the same code with no module behind it: pickled by value, so the worker needs none of this file
    probe = types.FunctionType(_package_fingerprint.__code__, {"__builtins__": builtins}, "covers_dist_fingerprint")
    here = _package_fingerprint()
    there = ray.get(ray.remote(num_cpus=0)(probe).remote())
    if there[1] != here[1]:
        raise RuntimeError(
            f"Ray's workers import covers_dist from {there[0]}, this command from {here[0]}, and their sources "
            f"differ (Ray puts the driver's current directory, {os.getcwd()}, first on its workers' path: a copy "
            "of the package there wins over the installed one). Run from a directory without another copy of "
            "the package, or install the copy you mean to run."
        )


#: Longest temp dir Ray's socket paths fit under (AF_UNIX: 107 bytes, of which Ray's session
#: directory and socket names take about 64).
_MAX_TEMP_DIR = 40


def ray_temp_dir() -> str:
    """A fresh temp dir for a local instance; under /tmp when ``TMPDIR`` is too long for Ray's
    socket paths."""
    tmp = tempfile.mkdtemp(prefix="covers-ray-")
    if len(tmp) > _MAX_TEMP_DIR and os.path.isdir("/tmp"):
        os.rmdir(tmp)
        tmp = tempfile.mkdtemp(prefix="covers-ray-", dir="/tmp")
    return tmp


def loopback_only() -> None:
    """Make Ray processes started from here bind and talk on 127.0.0.1 only (unless the caller set
    ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER`` otherwise). Ray reads the variable at import time, so it
    is also set on the already-imported constants module; the processes Ray spawns inherit it."""
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    if os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] == "0":
        from ray._private import ray_constants

        ray_constants.ENABLE_RAY_CLUSTER = False


def check_run_dir_outlives_the_job(run_dir: str) -> None:
    """Refuse a relative ``runtime.run_dir`` in a driver that ``ray job submit --working-dir``
    started: such a driver runs in Ray's per-job copy of the working directory, which Ray deletes
    when the job ends, and the run (its checkpoints included) would go with it."""
    import json

    from ..config import ConfigError

    job = os.environ.get("RAY_JOB_CONFIG_JSON_ENV_VAR")  # set by Ray's job supervisor for the entrypoint
    if not job or os.path.isabs(run_dir):
        return
    try:
        working_dir = (json.loads(job).get("runtime_env") or {}).get("working_dir")
    except (ValueError, AttributeError):
        return
    if working_dir:
        raise ConfigError(
            f"runtime.run_dir={run_dir!r} is relative, and this Ray job runs in Ray's temporary copy of its "
            f"working directory ({os.getcwd()}), which Ray deletes when the job ends: give an absolute path on "
            "storage that outlives the job, e.g. --run-dir /data/runs/NAME"
        )


def shutdown_ray(keep_logs: bool | None = None) -> str | None:
    """Shut down Ray if this process started it (a cluster we joined is left running) and remove
    the instance's temp dir. With ``keep_logs`` the dir stays, with Ray's logs; by default it stays
    when an exception is on its way (a ``finally`` after a failure), for a post-mortem. Returns the
    temp dir if it was kept."""
    global _STARTED_HERE, _TEMP_DIR
    import ray

    if not (ray.is_initialized() and _STARTED_HERE):
        return None
    ray.shutdown()
    _STARTED_HERE = False
    tmp, _TEMP_DIR = _TEMP_DIR, None
    if keep_logs is None:
        keep_logs = failing()
    if tmp and not keep_logs:
        shutil.rmtree(tmp, ignore_errors=True)
        return None
    return tmp


def failing() -> bool:
    """Whether an exception is on its way through the caller (called in a ``finally`` block)."""
    return sys.exc_info()[0] is not None


def resolve_weights(handle: Any) -> Any:
    """Weights as published by a backend: a state dict (serial) or ``[object ref]`` (Ray; wrapped
    in a list so that Ray passes the reference instead of resolving it for every call)."""
    if isinstance(handle, list):
        import ray

        return ray.get(handle[0])
    return handle
