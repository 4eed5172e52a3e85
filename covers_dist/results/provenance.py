"""Where a result came from: the code's commit and the machine's CPU.

Plain module (no Ray): the driver appends one line per start or resume to ``RUN/provenance.jsonl``
(:func:`record_start`), and result files carry :func:`code_commit` and :func:`cpu_model`.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

from .. import __version__

PROVENANCE = "provenance.jsonl"
PACKAGE_DIR = Path(__file__).resolve().parents[1]


def code_commit(path: str | os.PathLike = PACKAGE_DIR) -> dict[str, Any]:
    """``{"commit": sha or None, "dirty": bool or None}`` of the git checkout holding ``path``
    (None where the package is not in a checkout, e.g. installed from a wheel)."""
    try:
        sha = subprocess.run(
            ["git", "-C", str(path), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "-C", str(path), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": sha or None, "dirty": bool(status.strip())}


def cpu_model() -> str:
    """The CPU in one line: model name, family/model and the widest vector ISA (AVX-512, AVX2)."""
    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    fields: dict[str, str] = {}
    for line in info.splitlines():
        if ":" in line:
            key, value = line.split(":", 1)
            fields.setdefault(key.strip(), value.strip())
    if not fields:
        return platform.processor() or platform.machine() or "unknown"
    flags = fields.get("flags", "").split()
    isa = "AVX-512" if "avx512f" in flags else ("AVX2" if "avx2" in flags else "no AVX2")
    cores = os.cpu_count()
    return (
        f"{fields.get('model name', 'unknown')} (family {fields.get('cpu family', '?')} "
        f"model {fields.get('model', '?')}, {isa}, {cores} cores)"
    )


def record_start(run_dir: str | os.PathLike, resumed: bool) -> dict[str, Any]:
    """Append this resume of a run to ``RUN/provenance.jsonl`` (a new run starts the file anew);
    the line written."""
    entry = {
        "time_unix": time.time(),
        "resumed": bool(resumed),
        "version": __version__,
        **code_commit(),
        "cpu": cpu_model(),
    }
    with open(Path(run_dir) / PROVENANCE, "a" if resumed else "w") as fh:  # a new run starts the file
        fh.write(json.dumps(entry) + "\n")
    return entry


def read_starts(run_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The lines :func:`record_start` wrote ([] for a run that predates them)."""
    path = Path(run_dir) / PROVENANCE
    if not path.exists():
        return []
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
