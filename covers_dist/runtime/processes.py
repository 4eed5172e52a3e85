"""Which process runs which part of a run: ``processes/<role>-<index>.json`` in the run's storage.

Every Ray actor of a run (rollout and evaluation workers, learners, the clustering actor), the
driver and the HTTP service write one small record when they start (a restarted actor rewrites
its own), with their PID, host and, on Ray, node. The records go to the run's storage
(``runtime.storage``, :mod:`.run_storage`), which every node reaches. Operators use them to see
where things run; ``covers-dist bench chaos`` uses them to pick what to kill. Plain module: no Ray.
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path
from typing import Any

from ..storage import StorageError
from .run_storage import PROCESSES, open_storage

__all__ = ["announce", "list_processes", "running"]


def announce(storage: str | Path | None, role: str, index: int | None = None, **extra: Any) -> None:
    """Record this process as ``role`` (``index``: worker number or policy id) of the run whose
    storage is ``storage`` (a path or URI); ``extra``: more fields (e.g. the Ray node id)."""
    if not storage:
        return
    name = role if index is None else f"{role}-{index}"
    entry = {"role": role, "index": index, "pid": os.getpid(), "host": socket.gethostname(), "started": time.time(), **extra}
    open_storage(str(storage)).write_bytes(f"{PROCESSES}/{name}.json", json.dumps(entry).encode())


def list_processes(storage: str | Path) -> list[dict[str, Any]]:
    """The recorded processes of a run (newest record per role and index), sorted by name."""
    store = open_storage(str(storage))
    out = []
    for name in store.list(PROCESSES):
        if not name.endswith(".json"):
            continue
        try:
            out.append(json.loads(store.read_bytes(f"{PROCESSES}/{name}")))
        except (StorageError, OSError, json.JSONDecodeError):  # being replaced right now
            continue
    return out


def running(pid: int) -> bool:
    """A running process (not a zombie waiting for its parent to reap it)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")
