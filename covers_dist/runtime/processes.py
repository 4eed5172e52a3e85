"""Which process runs which part of a run: ``RUN_DIR/processes/<role>-<index>.json``.

Every Ray actor of a run (rollout and evaluation workers, learners, the clustering actor), the
driver and the HTTP service write one small file when they start (a restarted actor rewrites
its own), with their PID and host. Operators use it to see where things run; ``covers-dist
bench chaos`` uses it to pick what to kill. Plain module: no Ray.
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path
from typing import Any

__all__ = ["PROCESS_DIR", "announce", "list_processes", "running"]

PROCESS_DIR = "processes"


def announce(run_dir: str | Path | None, role: str, index: int | None = None, **extra: Any) -> None:
    """Record this process as ``role`` (``index``: worker number or policy id) of the run;
    ``extra``: more fields (e.g. the Ray node id)."""
    if not run_dir:
        return
    root = Path(run_dir) / PROCESS_DIR
    root.mkdir(parents=True, exist_ok=True)
    name = role if index is None else f"{role}-{index}"
    entry = {"role": role, "index": index, "pid": os.getpid(), "host": socket.gethostname(), "started": time.time(), **extra}
    tmp = root / f".{name}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(entry))
    os.replace(tmp, root / f"{name}.json")


def list_processes(run_dir: str | Path) -> list[dict[str, Any]]:
    """The recorded processes of a run (newest record per role and index), sorted by name."""
    root = Path(run_dir) / PROCESS_DIR
    if not root.is_dir():
        return []
    out = []
    for f in sorted(root.glob("*.json")):
        try:
            out.append(json.loads(f.read_text()))
        except (OSError, json.JSONDecodeError):  # being replaced right now
            continue
    return out


def running(pid: int) -> bool:
    """A running process (not a zombie waiting for its parent to reap it)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")
