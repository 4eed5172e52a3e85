"""A run's storage (``runtime.storage``, :mod:`covers_dist.storage`): what lives there and how
the driver keeps it and its local run directory in step.

Layout under the storage root::

    learners_live/policy-N.pt   each learner's whole state after its newest update (the learner writes it)
    clustering_live/state.tar   the bank and the clustering service's counters after each assignment
    processes/<role>.json       which process runs which part of the run (pid, node)
    checkpoints/ckpt-N/         copies of the driver's checkpoints (manifest.json written last)
    config.yaml, *.jsonl, ...   copies of the run's logs, refreshed with every checkpoint
    run.json                    the running driver's token: an actor that cannot read it does not
                                see this storage (a path only the driver's node has) and stops

Without ``runtime.storage`` the storage is ``runtime.run_dir`` itself: the live state sits beside
the checkpoints, and nothing is copied. With a URI, the run directory is the driver's local
working copy; a driver on a fresh node (a retried job, a rescheduled pod) fetches the newest
valid checkpoint and the logs from the storage before it resumes (:func:`fetch_run`).
"""

from __future__ import annotations

import functools
import json
import os
import secrets
import shutil
import socket
import tempfile
import time
from pathlib import Path
from typing import Callable

from ..config import Config
from ..storage import DEFAULT_RETRY_S, Storage, StorageError, is_uri
from .checkpoint import KEEP, CheckpointError, list_checkpoints, verify_checkpoint

__all__ = [
    "LEARNERS_LIVE",
    "CLUSTERING_LIVE",
    "PROCESSES",
    "storage_location",
    "open_storage",
    "run_store",
    "mirrors_run_dir",
    "drop_live_state",
    "push_checkpoint",
    "fetch_run",
    "storage_holds_a_run",
    "clear_storage",
    "mark_run",
    "check_reachable",
]

LEARNERS_LIVE = "learners_live"
CLUSTERING_LIVE = "clustering_live"
PROCESSES = "processes"
CHECKPOINTS = "checkpoints"
RUN_MARKER = "run.json"


def storage_location(cfg: Config, run_dir: str | Path | None = None) -> str:
    """``runtime.storage``, or the absolute run directory (``run_dir``, default ``runtime.run_dir``;
    absolute because actors may run in another directory)."""
    return cfg.runtime.storage or os.path.abspath(run_dir if run_dir is not None else cfg.runtime.run_dir)


@functools.lru_cache(maxsize=8)
def open_storage(location: str, retry_s: float = DEFAULT_RETRY_S) -> Storage:
    """One :class:`~covers_dist.storage.Storage` per location, retry budget and process (opening an
    object store's filesystem resolves its endpoint and credentials once)."""
    return Storage(location, retry_s=retry_s)


def run_store(cfg: Config) -> Storage:
    """The storage of the run of ``cfg``, with its retry budget (``runtime.storage_retry_s``)."""
    return open_storage(storage_location(cfg), cfg.runtime.storage_retry_s)


def mirrors_run_dir(cfg: Config) -> bool:
    """Whether checkpoints and logs are copied to a storage apart from the run directory."""
    where = cfg.runtime.storage
    if not where:
        return False
    if where.startswith("file://"):
        where = where[len("file://") :]
    elif is_uri(where):
        return True
    return not _same_dir(where, cfg.runtime.run_dir)


def _same_dir(a: str, b: str) -> bool:
    return os.path.realpath(a) == os.path.realpath(b)


def drop_live_state(cfg: Config, keep_policies: list[int] | None = None) -> None:
    """Remove live state an earlier run left: every learner's but those of ``keep_policies``
    (a resumed checkpoint's), and the clustering actor's unless a checkpoint is resumed."""
    store = run_store(cfg)
    kept = {f"policy-{pid}.pt" for pid in keep_policies or []}
    for name in store.list(LEARNERS_LIVE):
        if name not in kept:
            store.delete(f"{LEARNERS_LIVE}/{name}")
    if keep_policies is None:
        store.delete_dir(CLUSTERING_LIVE)


#: (storage key, (size, mtime)) of each log file this process copied to a storage: a checkpoint
#: copies only what changed since (the live logs; a rotated segment once), not every segment again.
_UPLOADED: dict[str, tuple[int, int]] = {}


def push_checkpoint(cfg: Config, path: Path) -> None:
    """Copy the checkpoint at ``path`` and the run's logs to the storage (when it is apart from
    the run directory); keep the newest ``KEEP`` checkpoints there."""
    if not mirrors_run_dir(cfg):
        return
    store = run_store(cfg)
    store.put_dir(path, f"{CHECKPOINTS}/{path.name}", last="manifest.json")
    for name in store.list_dirs(CHECKPOINTS)[:-KEEP]:
        store.delete_dir(f"{CHECKPOINTS}/{name}")
    run_dir = Path(cfg.runtime.run_dir)
    for f in sorted(run_dir.iterdir()):
        if f.is_file() and not f.name.startswith(".") and f.name != RUN_MARKER:  # the token is the driver's own
            stat = f.stat()
            key, seen = (store.describe(f.name), (stat.st_size, stat.st_mtime_ns))
            if _UPLOADED.get(key) == seen:  # unchanged since this process copied it (a closed log segment)
                continue
            store.write_bytes(f.name, f.read_bytes())
            _UPLOADED[key] = seen


def storage_holds_a_run(cfg: Config) -> bool:
    """Whether the storage (apart from the run directory) holds checkpoints of a run."""
    return mirrors_run_dir(cfg) and bool(run_store(cfg).list_dirs(CHECKPOINTS))


def fetch_run(cfg: Config, log: Callable[[str], None] = print) -> Path | None:
    """Bring the storage's newest valid checkpoint and the run's logs into the run directory
    when the run directory has no valid checkpoint of its own (a driver on a fresh node); the
    checkpoint's local path, or None when there was nothing to fetch."""
    run_dir = Path(cfg.runtime.run_dir)
    if not mirrors_run_dir(cfg) or any(_valid(p) for p in list_checkpoints(run_dir)):
        return None
    store = run_store(cfg)
    names = store.list_dirs(CHECKPOINTS)
    if not names:
        return None
    run_dir.mkdir(parents=True, exist_ok=True)
    for name in store.list(""):
        if name != RUN_MARKER:  # an earlier driver's token: never to be copied back over the running one's
            (run_dir / name).write_bytes(store.read_bytes(name))
    local = run_dir / CHECKPOINTS
    for name in reversed(names):
        tmp = Path(tempfile.mkdtemp(prefix=f".fetch-{name}-", dir=run_dir))
        try:
            store.get_dir(f"{CHECKPOINTS}/{name}", tmp)
            verify_checkpoint(tmp)
        except (CheckpointError, StorageError) as e:
            log(f"warning: {store.describe(CHECKPOINTS + '/' + name)}: {e}; trying the previous checkpoint")
            shutil.rmtree(tmp, ignore_errors=True)
            continue
        local.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(local / name, ignore_errors=True)  # a local copy that did not verify
        os.replace(tmp, local / name)
        log(f"fetched checkpoint {name} and the run's logs from {store.describe()} into {run_dir}")
        return local / name
    raise CheckpointError(f"{store.describe(CHECKPOINTS)} holds no valid checkpoint ({', '.join(names)})")


def _valid(path: Path) -> bool:
    try:
        verify_checkpoint(path)
        return True
    except CheckpointError:
        return False


def clear_storage(cfg: Config) -> None:
    """Remove an earlier run from the storage (apart from the run directory): ``--overwrite``."""
    if not mirrors_run_dir(cfg):
        return
    store = run_store(cfg)
    for key in (CHECKPOINTS, LEARNERS_LIVE, CLUSTERING_LIVE, PROCESSES):
        store.delete_dir(key)
    for name in store.list(""):
        store.delete(name)


def mark_run(storage: str) -> str:
    """Write a fresh token of this driver into ``storage`` (``run.json``); the actors it starts
    check it (:func:`check_reachable`)."""
    token = secrets.token_hex(8)
    entry = {"token": token, "host": socket.gethostname(), "pid": os.getpid(), "started": time.time()}
    open_storage(storage).write_bytes(RUN_MARKER, json.dumps(entry).encode())
    return token


def check_reachable(storage: str, token: str | None, what: str) -> None:
    """Stop ``what`` (an actor starting) unless it reads the driver's ``token`` in the storage: an
    actor whose node does not see the storage (a local path on a cluster whose nodes share no
    disk) would otherwise keep its state where no restart on another node finds it."""
    if not token:
        return
    store = open_storage(storage)
    try:
        found = json.loads(store.read_bytes(RUN_MARKER)).get("token")
    except (StorageError, OSError, ValueError, AttributeError):
        found = None
    if found != token:
        problem = "is missing" if found is None else "belongs to another run"
        raise StorageError(
            f"{what} on host {socket.gethostname()} does not see this run's storage {store.describe()} "
            f"({RUN_MARKER} {problem} there): on a cluster whose nodes share no disk, set runtime.storage to a "
            "URI every node reaches (s3://bucket/prefix, gs://bucket/prefix) or a path every node mounts"
        )
