"""Saving and restoring a :class:`~covers_dist.clustering.bank.PolicyBank`, atomically.

A checkpoint directory holds two files:

* ``buffers-<token>.npz``: every buffer's frames (``p<id>_image`` uint8, ``p<id>_proprio``
  float32; ``r<id>_...`` for retired policies), written to a temporary file, flushed, then renamed into place;
* ``bank.json``: everything else (settings, entries, retired entries and merges, buffer
  bookkeeping and RNG states, the full assignment history, the episode labels), plus the format name and version and the name and
  SHA-256 of the ``.npz`` it belongs to. It is written last, the same way (temporary file, fsync,
  ``os.replace``): its rename is the commit point.

A save that fails at any step leaves the previous ``bank.json`` and the ``.npz`` it names intact
(older ``.npz`` files are deleted only after the new ``bank.json`` is in place), so the previous
checkpoint stays loadable. Loading checks the format name and version, the presence and hash of
the ``.npz``, and the shapes of every array against the JSON; any problem raises
:class:`CheckpointError` (a ``ValueError``) that names the file and the problem, and no partially
restored bank is ever returned.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
from collections import Counter
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .assignment import AssignmentRecord
from .bank import PolicyBank
from .buffer import ObservationBuffer
from .features import FeatureFn
from .policy_entry import PolicyEntry

__all__ = ["CheckpointError", "save_bank", "load_bank", "FORMAT_NAME", "FORMAT_VERSION", "STATE_FILE"]

FORMAT_NAME = "covers-dist.policy-bank"
FORMAT_VERSION = 1
STATE_FILE = "bank.json"
_SETTINGS = ("metric", "threshold", "buffer_size", "replacement", "max_policies", "initial_frames", "feature_norm")
#: Decision-rule settings, with the values that banks saved before they existed are read as.
_RULE_SETTINGS: dict[str, Any] = {"rule": "threshold", "false_split_rate": 0.001, "calibration_samples": 200}
#: Healing settings, with the values of banks saved before healing existed
_HEAL_SETTINGS: dict[str, Any] = {"merge_threshold": None, "merge_every": 8, "tie_margin": 0.0}


class CheckpointError(ValueError):
    """A bank checkpoint is missing, corrupt, of another format version, or does not match."""


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file, read in 1 MiB chunks (shared with the run checkpoints)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_atomic(path: Path, write: Any) -> None:
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _entry_state(e: PolicyEntry, prefix: str, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    pid = e.policy_id
    if len(e.buffer):
        obs = e.buffer.observations()
        arrays[f"{prefix}{pid}_image"], arrays[f"{prefix}{pid}_proprio"] = obs["image"], obs["proprio"]
    return {
        "policy_id": pid,
        "buffer": e.buffer.state(),
        "created_at_episode": e.created_at_episode,
        "created_at_assignment": e.created_at_assignment,
        "created_at_time": e.created_at_time,
        "episodes": e.episodes,
        "assignments": e.assignments,
        "group_counts": [[g, c] for g, c in sorted(e.group_counts.items())],
        "episodes_reported": e.episodes_reported,
        "last_success": e.last_success,
        "last_return": e.last_return,
    }


def bank_state(bank: PolicyBank, history_from: int = 0) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The bank as (JSON-safe state, arrays); ``history_from``: the assignment records before it are
    left out (kept elsewhere, e.g. the clustering service's journal) and ``history_offset`` says so."""
    arrays: dict[str, np.ndarray] = {}
    entries = [_entry_state(bank.entries[pid], "p", arrays) for pid in bank.policy_ids]
    retired = [_entry_state(bank.retired[pid], "r", arrays) for pid in sorted(bank.retired)]
    state = {
        "settings": {
            k: getattr(bank, k) for k in _SETTINGS + ("mode", "seed") + tuple(_RULE_SETTINGS) + tuple(_HEAL_SETTINGS)
        },
        "calibration_rng": bank.calibration_rng.bit_generator.state,
        "current_policy_id": bank.current_policy_id,
        "next_episode": bank.next_episode,
        "entries": entries,
        "retired": retired,
        "merges": bank.merges,
        "history": [r.to_dict() for r in bank.history[history_from:]],
        "labels": [[e, p, g] for e, (p, g) in sorted(bank.labels.items())],
        "group_policy": [[g, p] for g, p in sorted(bank.group_policy.items())],
    }
    if history_from:
        state["history_offset"] = int(history_from)
    return state, arrays


def save_bank(bank: PolicyBank, directory: str | os.PathLike, history_from: int = 0) -> Path:
    """Write ``bank`` to ``directory`` (created if needed); returns the path of ``bank.json``.
    ``history_from``: see :func:`bank_state` (0: the whole history, as every checkpoint holds it)."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    state, arrays = bank_state(bank, history_from)
    npz = out / f"buffers-{secrets.token_hex(6)}.npz"
    _write_atomic(npz, lambda f: np.savez(f, **arrays))
    doc = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "buffers_file": npz.name,
        "buffers_sha256": file_sha256(npz),
        "state": state,
    }
    text = json.dumps(doc, allow_nan=False, sort_keys=True).encode()
    try:
        _write_atomic(out / STATE_FILE, lambda f: f.write(text))
    except BaseException:
        npz.unlink(missing_ok=True)
        raise
    _fsync_dir(out)
    for old in out.glob("buffers-*.npz"):
        if old.name != npz.name:
            old.unlink(missing_ok=True)
    return out / STATE_FILE


def _read_doc(directory: Path) -> dict[str, Any]:
    path = directory / STATE_FILE
    if not directory.is_dir():
        raise CheckpointError(f"bank checkpoint directory {str(directory)!r} does not exist")
    if not path.is_file():
        raise CheckpointError(f"no bank checkpoint in {str(directory)!r}: {STATE_FILE} is missing")
    try:
        doc = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{path}: corrupt bank state (not valid JSON: {e})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise CheckpointError(f"{path}: not a policy-bank checkpoint (format {doc.get('format') if isinstance(doc, dict) else doc!r})")
    if doc.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: format version {doc.get('format_version')!r} is not supported (expected {FORMAT_VERSION})"
        )
    return doc


def _read_arrays(directory: Path, doc: dict[str, Any]) -> dict[str, np.ndarray]:
    name = doc.get("buffers_file")
    if not isinstance(name, str) or "/" in name or not name.endswith(".npz"):
        raise CheckpointError(f"{directory / STATE_FILE}: bad buffers_file entry {name!r}")
    npz = directory / name
    if not npz.is_file():
        raise CheckpointError(f"bank checkpoint in {str(directory)!r} is incomplete: {name} is missing")
    if file_sha256(npz) != doc.get("buffers_sha256"):
        raise CheckpointError(f"{npz}: corrupt buffers (SHA-256 does not match {STATE_FILE})")
    try:
        with np.load(npz, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # zipfile / format errors
        raise CheckpointError(f"{npz}: unreadable buffers ({e})") from None


def load_bank(
    directory: str | os.PathLike,
    feature_fn: FeatureFn | None = None,
    config: Any = None,
    history_head: Callable[[int], list[dict[str, Any]]] | None = None,
) -> PolicyBank:
    """Restore a bank written by :func:`save_bank`.

    ``config`` (a :class:`covers_dist.config.Config`), when given, must agree with the saved
    settings (metric, threshold, buffer size, replacement, cap, initial frames, feature norm, mode,
    decision rule, and under the calibrated rule its false-split rate and samples);
    a difference raises :class:`CheckpointError` naming the fields. ``history_head(n)`` gives the
    first ``n`` assignment records of a bank saved with ``history_from=n`` (a live state whose
    earlier records are in a journal).
    """
    directory = Path(directory)
    doc = _read_doc(directory)
    arrays = _read_arrays(directory, doc)
    try:
        return _rebuild(doc["state"], arrays, feature_fn, config, history_head)
    except CheckpointError:
        raise
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise CheckpointError(f"{directory / STATE_FILE}: inconsistent bank state ({type(e).__name__}: {e})") from None


def _rebuild(
    state: dict[str, Any], arrays: dict[str, np.ndarray], feature_fn: Any, config: Any,
    history_head: Callable[[int], list[dict[str, Any]]] | None = None,
) -> PolicyBank:  # fmt: skip
    settings = {**_RULE_SETTINGS, **state["settings"]}  # banks saved before the rule settings existed
    if config is not None:
        expected = PolicyBank.from_config(config)
        keys = _SETTINGS + ("mode", "rule")
        if "calibrated" in (settings["rule"], expected.rule):
            keys += ("false_split_rate", "calibration_samples")
        diff = [f"{k}: saved {settings[k]!r}, config {getattr(expected, k)!r}" for k in keys
                if settings[k] != getattr(expected, k)]
        if diff:
            raise CheckpointError("bank checkpoint does not match the config: " + "; ".join(diff))
    bank = PolicyBank(feature_fn, **{**_HEAL_SETTINGS, **settings})
    for e in state["entries"]:
        entry = _entry(e, "p", arrays)
        bank.entries[entry.policy_id] = entry
        bank.episode_policy.update((x, entry.policy_id) for x in entry.episodes)
    for e in state.get("retired", []):  # absent in banks saved before healing
        entry = _entry(e, "r", arrays)
        bank.retired[entry.policy_id] = entry
    bank.merges = [dict(m) for m in state.get("merges", [])]
    bank.current_policy_id = state["current_policy_id"]
    if bank.current_policy_id is not None and bank.current_policy_id not in bank.entries:
        raise CheckpointError(f"current_policy_id {bank.current_policy_id} is not in the saved bank")
    bank.next_episode = int(state["next_episode"])
    offset = int(state.get("history_offset", 0))
    head: list[dict[str, Any]] = []
    if offset:  # the first records are kept apart (the clustering service's journal)
        if history_head is None:
            raise CheckpointError(f"the bank holds assignment records from {offset} on only, and no journal was given")
        head = history_head(offset)
        if len(head) != offset:
            raise CheckpointError(f"the journal holds {len(head)} assignment records, the bank expects {offset}")
    bank.history = [AssignmentRecord.from_dict(r) for r in [*head, *state["history"]]]
    bank.labels = {int(e): (int(p), int(g)) for e, p, g in state["labels"]}
    bank.rebuild_label_table()
    bank.group_policy = {int(g): int(p) for g, p in state["group_policy"]}
    if state.get("calibration_rng") is not None:  # absent in banks saved before the calibrated rule
        bank.calibration_rng.bit_generator.state = state["calibration_rng"]
    return bank


def _entry(e: dict[str, Any], prefix: str, arrays: dict[str, np.ndarray]) -> PolicyEntry:
    pid = int(e["policy_id"])
    size = int(e["buffer"]["size"])
    image = arrays.get(f"{prefix}{pid}_image", np.zeros((0, 1, 1, 3), np.uint8))
    proprio = arrays.get(f"{prefix}{pid}_proprio", np.zeros((0, 1), np.float32))
    if image.dtype != np.uint8 or proprio.dtype != np.float32 or image.shape[0] != size:
        raise CheckpointError(
            f"buffers of policy {pid}: arrays {image.dtype}{image.shape} / {proprio.dtype}{proprio.shape} "
            f"do not match the saved size {size}"
        )
    return PolicyEntry(
        policy_id=pid,
        buffer=ObservationBuffer.from_state(e["buffer"], image, proprio),
        created_at_episode=int(e["created_at_episode"]),
        created_at_assignment=int(e["created_at_assignment"]),
        created_at_time=float(e["created_at_time"]),
        episodes=[int(x) for x in e["episodes"]],
        assignments=int(e["assignments"]),
        group_counts=Counter({int(g): int(c) for g, c in e["group_counts"]}),
        episodes_reported=int(e["episodes_reported"]),
        last_success=e["last_success"],
        last_return=e["last_return"],
    )
