"""Atomic, verified run checkpoints.

Layout of ``RUN_DIR/checkpoints/``::

    ckpt-000012/            one complete checkpoint (iteration 12)
        manifest.json       format version, iteration, and the sha256 of every other file
        driver.json         counters, stream position, the latest success per group
        config.yaml         the run's config
        bank/               the policy bank (covers_dist.clustering persistence format)
        learners/policy-N.pt  model + optimizer + schedule state of each learner (torch.save)
        learners/sampling-N.pt  pipelined loop only: the weights policy N samples with until the
                            update in flight when the checkpoint was written is published

A checkpoint is written into a hidden temporary directory and renamed into place only when every
file is written and hashed, so a crash leaves either the old or the new checkpoint, never half of
one. :func:`latest_valid_checkpoint` checks hashes and falls back to the previous checkpoint with
a message when the newest one is corrupt. Policy weights are saved with the models' documented
state-dict mode (see ``covers_dist.models``).
"""

from __future__ import annotations

import io
import json
import os
import pickle
import shutil
from pathlib import Path
from typing import Any, Callable

from ..clustering.persistence import STATE_FILE as BANK_INDEX  # the file every saved bank holds
from ..clustering.persistence import CheckpointError, file_sha256  # one error type, one hash

__all__ = [
    "CheckpointError",
    "write_checkpoint",
    "latest_valid_checkpoint",
    "verify_checkpoint",
    "list_checkpoints",
    "load_state",
]

FORMAT_VERSION = 1
KEEP = 3


def _files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() and p.name != "manifest.json")


def write_checkpoint(run_dir: str | Path, iteration: int, writer: Callable[[Path], None]) -> Path:
    """Create ``ckpt-<iteration>`` atomically; ``writer(tmp_dir)`` writes the payload files."""
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    final = root / f"ckpt-{iteration:06d}"
    tmp = root / f".tmp-ckpt-{iteration:06d}-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        writer(tmp)
        manifest = {
            "format_version": FORMAT_VERSION,
            "iteration": iteration,
            "files": {str(p.relative_to(tmp)): file_sha256(p) for p in _files(tmp)},
        }
        with open(tmp / "manifest.json", "w") as fh:
            json.dump(manifest, fh, indent=1)
            fh.flush()
            os.fsync(fh.fileno())
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for old in list_checkpoints(run_dir)[:-KEEP]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def list_checkpoints(run_dir: str | Path) -> list[Path]:
    """Complete-looking checkpoint directories, oldest first."""
    root = Path(run_dir) / "checkpoints"
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and p.name.startswith("ckpt-"))


def verify_checkpoint(path: str | Path) -> dict[str, Any]:
    """The manifest of a checkpoint whose every file is present with its recorded hash."""
    path = Path(path)
    mf = path / "manifest.json"
    if not mf.is_file():
        raise CheckpointError(f"checkpoint {path.name}: manifest.json is missing (partial checkpoint)")
    try:
        manifest = json.loads(mf.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"checkpoint {path.name}: manifest.json is corrupt ({e})") from e
    if manifest.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {path.name}: format version {manifest.get('format_version')!r}, expected {FORMAT_VERSION}"
        )
    files = manifest.get("files", {})
    for rel, digest in files.items():
        f = path / rel
        if not f.is_file():
            raise CheckpointError(f"checkpoint {path.name}: file {rel} is missing")
        if file_sha256(f) != digest:
            raise CheckpointError(f"checkpoint {path.name}: file {rel} is corrupt (checksum mismatch)")
    missing = [rel for rel in needed_files(path) if rel not in files]
    if missing:
        raise CheckpointError(f"checkpoint {path.name}: the manifest lacks {', '.join(missing)}, which a restore needs")
    return manifest


def needed_files(path: Path) -> list[str]:
    """What a restore reads: the driver's state, the config, the bank and each policy's learner."""
    needed = ["driver.json", "config.yaml", f"bank/{BANK_INDEX}"]
    try:
        policies = json.loads((path / "driver.json").read_text()).get("policies", [])
    except (OSError, ValueError, AttributeError):
        return needed  # driver.json is missing or unreadable: reported as missing from the manifest
    return needed + [f"learners/policy-{int(pid)}.pt" for pid in policies]


def latest_valid_checkpoint(run_dir: str | Path, log: Callable[[str], None] = print) -> Path | None:
    """The newest checkpoint that verifies; corrupt newer ones are reported and skipped."""
    for path in reversed(list_checkpoints(run_dir)):
        try:
            verify_checkpoint(path)
            return path
        except CheckpointError as e:
            log(f"warning: {e}; falling back to the previous checkpoint")
    return None


def load_state(source: str | Path | bytes, where: str, map_location: Any = "cpu") -> Any:
    """A learner's or policy's saved state (``torch.save`` of tensors in plain containers), read
    without running any code the file may carry.

    A run directory and its storage are data, never code: the file is unpickled with
    ``torch.load(weights_only=True)``, which admits tensors, numbers, strings and the built-in
    containers only. Anything else (a pickled object, a callable) raises :class:`CheckpointError`
    naming ``where`` and what was refused, before any of it runs; so does a file that is not a torch
    file at all.
    """
    import torch

    handle = io.BytesIO(source) if isinstance(source, bytes) else source
    try:
        return torch.load(handle, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
        reason = next((ln for ln in lines if "unsupported" in ln.lower()), lines[0] if lines else type(e).__name__)
        raise CheckpointError(
            f"{where} is refused: it is not a torch file of tensors and plain containers ({reason}); "
            "covers-dist never runs code from a run directory or its storage"
        ) from None
    except (RuntimeError, EOFError, OSError, ValueError) as e:
        raise CheckpointError(f"{where} is unreadable ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else e})") from e
