"""Append-only JSONL logs that rotate into gzip segments, their reader, and resume truncation.

A log ``NAME`` (e.g. ``episodes.jsonl``) is the live file ``RUN_DIR/NAME`` plus up to ``keep``
closed segments ``NAME.<seq>.gz`` (``seq`` counts up; the lowest is the oldest). When the live
file reaches ``rotate_bytes`` it is renamed to ``NAME.<seq>``, a new live file is opened, and the
segment is compressed to ``NAME.<seq>.gz`` (written to a temp file, then renamed) before the
plain copy is removed; the oldest segments beyond ``keep`` are deleted. A process killed in the
middle leaves either the plain or the compressed segment complete; the next writer finishes
the job. :func:`read_jsonl_segments` reads the kept segments oldest first, then the live file.
"""

from __future__ import annotations

import gzip
import json
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = [
    "JsonlLog",
    "read_jsonl_file",
    "read_jsonl_segments",
    "remove_log",
    "segment_paths",
    "truncate_after_iteration",
]


def _segments(run_dir: Path, name: str) -> dict[int, list[Path]]:
    """{seq: [paths]} of the closed segments of ``name`` (plain, compressed or both)."""
    pattern = re.compile(rf"^{re.escape(name)}\.(\d+)(\.gz)?$")
    found: dict[int, list[Path]] = {}
    if run_dir.is_dir():
        for p in run_dir.iterdir():
            m = pattern.match(p.name)
            if m:
                found.setdefault(int(m.group(1)), []).append(p)
    return found


def segment_paths(run_dir: str | Path, name: str) -> list[Path]:
    """The closed segments of log ``name``, oldest first (a segment still being compressed is
    its plain file; a finished one its ``.gz``)."""
    found = _segments(Path(run_dir), name)
    return [max(found[seq], key=lambda p: p.suffix == ".gz") for seq in sorted(found)]


def remove_log(run_dir: str | Path, name: str) -> None:
    """Delete log ``name``: the live file and every segment (a run started over)."""
    run = Path(run_dir)
    for paths in _segments(run, name).values():
        for p in paths:
            p.unlink(missing_ok=True)
    (run / name).unlink(missing_ok=True)


def _open_text(path: Path):  # noqa: ANN202 - a text file object
    return gzip.open(path, "rt") if path.suffix == ".gz" else open(path)


def read_jsonl_file(path: str | Path, strict: bool = True, live: bool = True) -> Iterator[dict[str, Any]]:
    """Rows of one JSONL file, plain or ``.gz``.

    A line that is not a JSON object raises ``ValueError`` naming the file and line
    (``strict=False``: it is skipped). An unfinished last line (no newline: an interrupted append)
    is skipped in a ``live`` file and an error in a closed segment when ``strict``.
    """
    path = Path(path)
    with _open_text(path) as fh:
        for n, line in enumerate(fh, 1):
            if not line.endswith("\n"):  # only the last line can lack its newline
                if strict and not live and line.strip():
                    raise ValueError(f"{path}:{n} is an unfinished line")
                return
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError as e:
                if strict:
                    raise ValueError(f"{path}:{n} is not valid JSON ({e})") from None
                continue
            if isinstance(row, dict):
                yield row
            elif strict:
                raise ValueError(f"{path}:{n} is not a JSON object")


def has_log(run_dir: str | Path, name: str) -> bool:
    """Whether ``run_dir`` holds log ``name``: its live file or a kept segment."""
    return (Path(run_dir) / name).is_file() or bool(segment_paths(run_dir, name))


def read_jsonl_segments(run_dir: str | Path, name: str, strict: bool = True) -> Iterator[dict[str, Any]]:
    """Rows of log ``name`` in ``run_dir``: the kept segments oldest first, then the live file
    (see :func:`read_jsonl_file` for ``strict``). No live file and no segment: nothing."""
    run = Path(run_dir)
    for path in segment_paths(run, name):
        yield from read_jsonl_file(path, strict, live=False)
    if (run / name).is_file():
        yield from read_jsonl_file(run / name, strict, live=True)


def _compress(plain: Path) -> Path:
    """``NAME.<seq>`` -> ``NAME.<seq>.gz`` (temp file + rename), then the plain file is removed."""
    target = plain.with_name(plain.name + ".gz")
    tmp = plain.with_name(plain.name + ".gz.tmp")
    with open(plain, "rb") as src, gzip.open(tmp, "wb", compresslevel=6) as dst:
        shutil.copyfileobj(src, dst, 1 << 20)
    os.replace(tmp, target)
    plain.unlink()
    return target


def _drop_unfinished_tail(path: Path) -> None:
    """Cut a live file back to its last newline (the rest is a row whose append never finished)."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    with open(path, "rb+") as fh:
        fh.seek(-1, os.SEEK_END)
        if fh.read(1) == b"\n":
            return
        fh.seek(0)
        data = fh.read()
        fh.truncate(data.rfind(b"\n") + 1)


class JsonlLog:
    """``JsonlLog(path, rotate_bytes, keep)``: ``write(rows)`` appends one JSON line per row;
    ``rotate_bytes=None`` never rotates; ``keep`` is the most closed segments kept (0: none)."""

    def __init__(self, path: str | Path, rotate_bytes: int | None = None, keep: int = 5) -> None:
        if rotate_bytes is not None and rotate_bytes <= 0:
            raise ValueError(f"rotate_bytes={rotate_bytes!r} must be > 0 (None: never rotate)")
        if keep < 0:
            raise ValueError(f"keep={keep!r} must be >= 0")
        self.path = Path(path)
        self.rotate_bytes, self.keep = rotate_bytes, keep
        for seq, paths in _segments(self.path.parent, self.path.name).items():
            plain = self.path.with_name(f"{self.path.name}.{seq}")
            if plain in paths:  # a rotation interrupted before its compression finished
                _compress(plain)
        self._prune()
        _drop_unfinished_tail(self.path)
        self._fh = open(self.path, "ab")
        self._size = self._fh.tell()

    def write(self, rows: list[dict[str, Any]]) -> None:
        """Append ``rows`` (flushed before returning); rotates when the live file reaches the limit."""
        for row in rows:
            line = (json.dumps(row, default=float) + "\n").encode()
            self._fh.write(line)
            self._size += len(line)
            if self.rotate_bytes is not None and self._size >= self.rotate_bytes:
                self.rotate()
        self._fh.flush()

    def rotate(self) -> None:
        """Close the live file as the next segment, compress it, drop segments beyond ``keep``."""
        self._fh.close()
        found = _segments(self.path.parent, self.path.name)
        plain = self.path.with_name(f"{self.path.name}.{max(found, default=0) + 1}")
        os.replace(self.path, plain)
        self._fh = open(self.path, "ab")
        self._size = 0
        _compress(plain)
        self._prune()

    def _prune(self) -> None:
        found = _segments(self.path.parent, self.path.name)
        for seq in sorted(found)[: max(len(found) - self.keep, 0)]:
            for p in found[seq]:
                p.unlink(missing_ok=True)

    def close(self) -> None:
        self._fh.close()


def _rewrite(path: Path, lines: list[bytes]) -> None:
    """Replace ``path`` by ``lines`` atomically (temp file + rename); an empty segment is removed."""
    if path.suffix == ".gz" and not lines:
        path.unlink()
        return
    tmp = path.with_name(path.name + ".tmp")
    with (gzip.open(tmp, "wb") if path.suffix == ".gz" else open(tmp, "wb")) as fh:
        fh.writelines(lines)
    os.replace(tmp, path)


def truncate_after_iteration(run_dir: str | Path, name: str, iteration: int) -> int:
    """Remove the rows whose ``"iteration"`` is above ``iteration`` from log ``name`` (the live file
    and, newest first, any segment that holds such rows); returns how many were removed.

    Each file is rewritten atomically. Rows without an ``"iteration"`` key and lines that do not
    parse are kept, except the live file's unfinished last line, which is dropped.
    """
    run = Path(run_dir)
    live = run / name
    _drop_unfinished_tail(live)
    files = ([live] if live.is_file() else []) + segment_paths(run, name)[::-1]
    removed = 0
    for path in files:
        with (gzip.open(path, "rb") if path.suffix == ".gz" else open(path, "rb")) as fh:
            lines = fh.read().splitlines(keepends=True)
        kept = [ln for ln in lines if not _after(ln, iteration)]
        removed += len(lines) - len(kept)
        if len(kept) != len(lines):
            _rewrite(path, kept)
        elif path != live:
            break  # segments are in iteration order: older ones hold nothing later
    return removed


def _after(line: bytes, iteration: int) -> bool:
    try:
        row = json.loads(line)
    except json.JSONDecodeError:
        return False
    it = row.get("iteration") if isinstance(row, dict) else None
    return isinstance(it, (int, float)) and not isinstance(it, bool) and it > iteration
