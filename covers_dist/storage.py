"""Where a run's durable state lives: a local directory or a ``pyarrow.fs`` URI.

``runtime.storage`` names it the way Ray Train's ``storage_path`` does: a local path
(``/data/runs/x``, ``file:///data/runs/x``) or a URI of any filesystem pyarrow speaks
(``s3://bucket/prefix``, ``gs://bucket/prefix``; an S3-compatible server with
``s3://bucket/prefix?endpoint_override=HOST:PORT&scheme=http``). Every process of a run reaches
the same storage by its URI, so no process relies on a file that only its own node can see:
the learners' and the clustering actor's live state, the process records and the copies of the
checkpoints and logs go through :class:`Storage`.

Each object is written whole: a local file through a temporary file and a rename, an object
store's object in one upload, so a reader sees the old or the new object, never half of one.

Faults: an object store's errors (a server away, a timeout, throttling) are retried with
exponential backoff for up to ``retry_s`` seconds, each retry logged; past that the operation
raises :class:`StorageUnavailable`. A local disk that is full (or read-only, or over quota) raises
:class:`StorageFull` at once, naming the disk and the object. A missing object is
:class:`ObjectMissing`, never retried. Every message has the location's credentials redacted.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import sys
import tarfile
import time
from pathlib import Path
from typing import Any, Callable, Iterator, TypeVar

T = TypeVar("T")

__all__ = [
    "Storage",
    "StorageError",
    "StorageUnavailable",
    "StorageFull",
    "ObjectMissing",
    "DEFAULT_RETRY_S",
    "is_uri",
    "storage_child",
    "pack_dir",
    "unpack_dir",
    "redact_uri",
    "uri_credentials",
    "SECRET_PARAMS",
]

#: Query parameters of a storage URI that carry credentials (pyarrow's S3 and GCS options): never
#: printed, logged or saved; give credentials in the environment (AWS_ACCESS_KEY_ID, ...) instead.
SECRET_PARAMS = ("access_key", "secret_key", "session_token", "access_token", "credential_token")


class StorageError(RuntimeError):
    """Storage that cannot be opened or used, or an object it should hold and does not."""


class ObjectMissing(StorageError):
    """An object the storage should hold and does not."""


class StorageUnavailable(StorageError):
    """An object store that kept failing for the whole retry budget (``retry_s``)."""


class StorageFull(StorageError):
    """A local disk with no room left (or read-only, or over quota) for an object being written."""


#: How long an object store's failing operation is retried before :class:`StorageUnavailable`.
DEFAULT_RETRY_S = 120.0
_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG}
#: Object-store errors that waiting does not mend (a wrong bucket or credentials): never retried.
PERMANENT = ("NO_SUCH_BUCKET", "NoSuchBucket", "ACCESS_DENIED", "AccessDenied", "INVALID_ACCESS_KEY_ID",
             "InvalidAccessKeyId", "SIGNATURE_DOES_NOT_MATCH", "SignatureDoesNotMatch", "INVALID_BUCKET_NAME",
             "Forbidden")  # fmt: skip


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def is_uri(location: str) -> bool:
    """Whether ``location`` names a filesystem by scheme (``s3://...``) rather than a local path."""
    return "://" in location


def uri_credentials(location: str) -> list[str]:
    """What in ``location`` is a credential: ``user:password@`` before the host, and any query
    parameter of :data:`SECRET_PARAMS` (their names only; empty for a URI that carries none)."""
    if not is_uri(location):
        return []
    from urllib.parse import parse_qsl, urlsplit

    parts = urlsplit(location)
    found = ["user:password@"] if "@" in parts.netloc else []
    return found + [k for k, _ in parse_qsl(parts.query, keep_blank_values=True) if k.lower() in SECRET_PARAMS]


def redact_uri(location: str) -> str:
    """``location`` for messages and logs: credentials before the host and secret query values
    replaced by ``***`` (the rest of the query, an endpoint say, kept)."""
    if not uri_credentials(location):
        return location
    from urllib.parse import parse_qsl, urlsplit, urlunsplit

    parts = urlsplit(location)
    netloc = f"***@{parts.netloc.rsplit('@', 1)[1]}" if "@" in parts.netloc else parts.netloc
    query = "&".join(
        f"{k}=***" if k.lower() in SECRET_PARAMS else f"{k}={v}"
        for k, v in parse_qsl(parts.query, keep_blank_values=True)
    )
    return urlunsplit((parts.scheme, netloc, parts.path, query, parts.fragment))


class Storage:
    """Read and write whole objects under one root (a local directory or a ``pyarrow.fs`` URI)."""

    def __init__(
        self, location: str | Path, retry_s: float = DEFAULT_RETRY_S, log: Callable[[str], None] = _stderr
    ) -> None:
        import pyarrow.fs as pafs

        self.retry_s, self.log = float(retry_s), log
        location = str(location)
        if not location:
            raise StorageError("storage location is empty: give a local path or a URI such as s3://bucket/prefix")
        if is_uri(location):
            try:
                self.fs, root = pafs.FileSystem.from_uri(location)
            except Exception as e:  # noqa: BLE001 - pyarrow raises ArrowInvalid, OSError or ValueError here
                raise StorageError(f"cannot open storage {_without_query(location)}: {_scrub(str(e), location)}") from None
        else:
            self.fs, root = pafs.LocalFileSystem(), os.path.abspath(location)
        self.location = location
        self.root = root.rstrip("/") or "/"
        self.local = isinstance(self.fs, pafs.LocalFileSystem)
        self._pafs = pafs

    def __repr__(self) -> str:
        return f"Storage({_without_query(self.location)!r})"

    def _path(self, key: str) -> str:
        key = key.strip("/")
        return f"{self.root}/{key}" if key else self.root

    # ---- objects ---------------------------------------------------------------------------------
    def _attempt(self, what: str, key: str, op: Callable[[], T]) -> T:
        """``op()``, retried with backoff while an object store fails (see the module docs)."""
        delay, tries = 0.25, 0
        deadline = time.monotonic() + self.retry_s
        while True:
            try:
                return op()
            except FileNotFoundError as e:
                raise ObjectMissing(f"{self.describe(key)} is missing") from e
            except OSError as e:
                reason = _scrub(f"{type(e).__name__}: {e}", self.location)
                if getattr(e, "errno", None) in _FULL:
                    raise StorageFull(f"no room to {what} {self.describe(key)}: {reason}") from None
                if self.local or any(m in str(e) for m in PERMANENT):  # waiting would not mend it
                    raise StorageError(f"cannot {what} {self.describe(key)}: {reason}") from None
                tries += 1
                if time.monotonic() + delay > deadline:
                    raise StorageUnavailable(
                        f"storage {self.describe()} kept failing for {self.retry_s:g} s ({tries} tries) "
                        f"to {what} {key}: {reason}"
                    ) from None
                self.log(f"storage {self.describe()}: {what} {key} failed ({reason}); retry {tries} in {delay:.2g} s")
                time.sleep(delay)
                delay = min(delay * 2, 8.0)

    def write_bytes(self, key: str, data: bytes) -> None:
        """Write the object ``key`` whole (replacing it)."""
        self._attempt("write", key, lambda: self._write(key, data))

    def _write(self, key: str, data: bytes) -> None:
        path = self._path(key)
        parent, name = path.rsplit("/", 1)
        if self.local:
            os.makedirs(parent, exist_ok=True)
            tmp = f"{parent}/.{name}.{os.getpid()}.tmp"
            try:
                with open(tmp, "wb") as fh:
                    fh.write(data)
                os.replace(tmp, path)  # a crash leaves the old or the new file, never half of one
            except OSError:
                with contextlib.suppress(OSError):
                    os.remove(tmp)
                raise
            return
        with self.fs.open_output_stream(path) as out:  # an object store's object appears whole on close
            out.write(data)

    def read_bytes(self, key: str) -> bytes:
        """The object ``key``; :class:`ObjectMissing` (a :class:`StorageError`) if it is missing."""

        def read() -> bytes:
            with self.fs.open_input_stream(self._path(key)) as fh:
                return fh.readall()

        return self._attempt("read", key, read)

    def exists(self, key: str) -> bool:
        return self._attempt("look up", key, lambda: self.fs.get_file_info(self._path(key)).type) == self._pafs.FileType.File

    def delete(self, key: str) -> None:
        """Remove the object ``key`` (nothing if it is missing)."""
        if self.exists(key):
            with contextlib.suppress(ObjectMissing):  # removed meanwhile
                self._attempt("delete", key, lambda: self.fs.delete_file(self._path(key)))

    def delete_dir(self, key: str) -> None:
        """Remove everything under ``key`` (nothing if there is nothing)."""
        info = self._attempt("look up", key, lambda: self.fs.get_file_info(self._path(key)))
        if info.type == self._pafs.FileType.Directory:
            self._attempt("delete", key, lambda: self.fs.delete_dir(self._path(key)))

    def _infos(self, key: str, recursive: bool) -> Any:
        selector = self._pafs.FileSelector(self._path(key), allow_not_found=True, recursive=recursive)
        return self._attempt("list", key, lambda: self.fs.get_file_info(selector))

    def list(self, key: str, recursive: bool = False) -> list[str]:
        """Names of the objects under ``key`` (relative to it, sorted); hidden temporaries left out."""
        base = self._path(key)
        out = []
        for info in self._infos(key, recursive):
            if info.type != self._pafs.FileType.File:
                continue
            rel = info.path[len(base) :].lstrip("/")
            if not any(part.startswith(".") for part in rel.split("/")):
                out.append(rel)
        return sorted(out)

    def list_dirs(self, key: str) -> list[str]:
        """Names of the directories (prefixes) right under ``key``, sorted."""
        base = self._path(key)
        return sorted(
            info.path[len(base) :].strip("/")
            for info in self._infos(key, False)
            if info.type == self._pafs.FileType.Directory
        )

    # ---- directories -----------------------------------------------------------------------------
    def put_dir(self, local_dir: str | Path, key: str, last: str | None = None) -> None:
        """Copy every file of ``local_dir`` to ``key/``; ``last``: a file written after all others
        (a manifest: a reader that sees it sees the rest)."""
        files = sorted(p for p in Path(local_dir).rglob("*") if p.is_file())
        for p in sorted(files, key=lambda p: p.name == last):
            self.write_bytes(f"{key}/{p.relative_to(local_dir).as_posix()}", p.read_bytes())

    def get_dir(self, key: str, local_dir: str | Path) -> list[str]:
        """Copy every object under ``key/`` into ``local_dir``; the names copied."""
        names = self.list(key, recursive=True)
        for rel in names:
            target = Path(local_dir) / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(self.read_bytes(f"{key}/{rel}"))
        return names

    def describe(self, key: str = "") -> str:
        """Where ``key`` is, for messages (a URI's query, which may hold an endpoint, left out)."""
        base = _without_query(self.location).rstrip("/")
        return f"{base}/{key.strip('/')}" if key else base


def storage_child(location: str, name: str) -> str:
    """The location ``name`` under ``location`` (a path or URI; a URI's query is kept)."""
    base, sep, query = location.partition("?")
    return f"{base.rstrip('/')}/{name}{sep}{query}"


def _without_query(location: str) -> str:
    """``location`` without its query (which may hold an endpoint) or credentials before the host."""
    return redact_uri(location.split("?", 1)[0])


def _scrub(message: str, location: str) -> str:
    """``message`` (a filesystem library's error about ``location``) with every credential the
    location carries replaced by ``***``."""
    from urllib.parse import parse_qsl, unquote, urlsplit

    if not uri_credentials(location):
        return message
    parts = urlsplit(location)
    secrets_ = [v for k, v in parse_qsl(parts.query) if k.lower() in SECRET_PARAMS]
    if "@" in parts.netloc:
        userinfo = parts.netloc.rsplit("@", 1)[0]
        secrets_ += [userinfo, unquote(userinfo), *userinfo.split(":", 1), *unquote(userinfo).split(":", 1)]
    for secret in sorted({s for s in secrets_ if s}, key=len, reverse=True):
        message = message.replace(secret, "***")
    return message


def pack_dir(directory: str | Path) -> bytes:
    """The files of ``directory`` as one uncompressed tar (one object to store or send whole)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for p in sorted(Path(directory).rglob("*")):
            if p.is_file():
                tar.add(p, arcname=p.relative_to(directory).as_posix(), recursive=False)
    return buf.getvalue()


def unpack_dir(data: bytes, directory: str | Path) -> list[str]:
    """Unpack :func:`pack_dir`'s bytes into ``directory``; the names unpacked. Only plain files
    with relative names inside ``directory`` are accepted."""
    out = []
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        for member in _members(tar):
            target = Path(directory) / member.name
            target.parent.mkdir(parents=True, exist_ok=True)
            src = tar.extractfile(member)
            assert src is not None
            target.write_bytes(src.read())
            out.append(member.name)
    return out


def _members(tar: tarfile.TarFile) -> Iterator[tarfile.TarInfo]:
    for member in tar.getmembers():
        parts = Path(member.name).parts
        if not member.isfile() or Path(member.name).is_absolute() or ".." in parts:
            raise StorageError(f"refusing archive member {member.name!r}: only relative plain files are stored")
        yield member
