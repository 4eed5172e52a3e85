"""One writer per run: the driver's lease on the run's storage.

A driver takes the lease before it writes anything of the run (live state, checkpoints, logs) and
keeps it while it runs: ``.driver-lease.json`` at the root of the run's storage (``runtime.storage``,
or the run directory) names the holder (host, PID, a random id, when it started) and a counter the
holder renews every ``ttl / 3`` seconds. A second driver on the same run refuses, with a message
naming the first, as long as the lease is renewed. A lease that is not renewed for ``ttl`` seconds
has expired (its driver died, or lost the storage) and is taken over; one left by a process of this
host that no longer exists is taken over at once. The renewal counter, not the clocks, decides: a
driver on another host with a skewed clock neither steals a live lease nor waits on a dead one for
longer than ``ttl`` (a lease whose timestamp is older than ``2 * ttl`` by this host's clock is
expired without waiting).

Object stores have no atomic create, so after writing its lease a driver reads it back: two
drivers that started at the same moment see one holder, and the other refuses. A holder that finds
another's id in the lease (a driver that took over after this one stalled for longer than ``ttl``)
marks it ``lost``: the loop stops with :class:`LeaseHeld` instead of writing on.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
import uuid
from typing import Any, Callable

from ..storage import ObjectMissing, Storage, StorageError
from .processes import running

__all__ = ["RunLease", "LeaseHeld", "LEASE"]

#: The lease's object at the root of the run's storage (hidden: never listed, copied or uploaded).
LEASE = ".driver-lease.json"

#: Lease ids held by this process: a second driver of one run in the same process is refused at once.
_HELD: set[str] = set()
_HELD_LOCK = threading.Lock()


class LeaseHeld(RuntimeError):
    """Another driver holds (or took over) the run's lease."""


def describe_holder(lease: dict[str, Any]) -> str:
    """The holder of ``lease`` for messages: ``PID 123 on host h (since 2026-12-07 23:31:04 UTC)``."""
    started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(float(lease.get("started", 0))))
    return f"PID {lease.get('pid')} on host {lease.get('host')} (since {started})"


class RunLease:
    """The lease on the run in ``storage`` (a :class:`~covers_dist.storage.Storage`) for this driver."""

    def __init__(self, storage: Storage, ttl_s: float = 60.0, log: Callable[[str], None] = print) -> None:
        if not ttl_s > 0:
            raise ValueError(f"ttl_s must be > 0, got {ttl_s}")
        self.storage, self.ttl_s, self.log = storage, float(ttl_s), log
        self.id = uuid.uuid4().hex
        self.record = {"id": self.id, "host": socket.gethostname(), "pid": os.getpid(), "started": time.time(), "renewals": 0}
        self.lost = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ---- the lease object -----------------------------------------------------------------------
    def read(self) -> dict[str, Any] | None:
        """The lease as stored, or None when there is none (an unreadable one counts as none)."""
        try:
            data = self.storage.read_bytes(LEASE)
        except ObjectMissing:
            return None
        try:
            lease = json.loads(data)
        except ValueError:
            return None
        return lease if isinstance(lease, dict) and "id" in lease else None

    def _write(self) -> None:
        self.record["renewed"] = time.time()
        self.storage.write_bytes(LEASE, json.dumps(self.record).encode())

    def _expired(self, lease: dict[str, Any], wait: Callable[[float], None]) -> bool:
        """Whether ``lease`` (another driver's) is dead: its process gone (this host), its stamp
        older than ``2 * ttl``, or no renewal seen within ``ttl``."""
        if lease.get("host") == self.record["host"]:
            pid = int(lease.get("pid", -1))
            if pid == os.getpid():
                with _HELD_LOCK:
                    return lease["id"] not in _HELD  # a driver of this process that ended without releasing
            if not running(pid):  # gone, or a zombie
                return True
        if time.time() - float(lease.get("renewed", 0)) > 2 * self.ttl_s:
            return True
        deadline = time.monotonic() + self.ttl_s
        while time.monotonic() < deadline:
            wait(min(self.ttl_s / 6, max(0.0, deadline - time.monotonic())))
            now = self.read()
            if now is None or now.get("id") != lease["id"] or now.get("renewals") != lease.get("renewals"):
                return now is None  # renewed (or another took it over): held; released: free
        return True

    # ---- taking, keeping, giving back ------------------------------------------------------------
    def acquire(self, wait: Callable[[float], None] = time.sleep) -> "RunLease":
        """Take the lease, or raise :class:`LeaseHeld` naming the driver that holds it."""
        where = self.storage.describe(LEASE)
        held = self.read()
        if held is not None and held.get("id") != self.id:
            if not self._expired(held, wait):
                raise LeaseHeld(
                    f"another driver holds this run: {describe_holder(held)}; its lease {where} was renewed "
                    f"within the last {self.ttl_s:g} s (runtime.lease_ttl_s). Stop it first, or wait until its "
                    "lease expires if it died"
                )
            self.log(f"note: the lease of {describe_holder(held)} on this run had expired; taking it over")
        self._write()
        wait(min(0.2, self.ttl_s / 10))
        now = self.read()
        if now is None or now.get("id") != self.id:
            raise LeaseHeld(
                f"another driver took this run at the same moment: "
                f"{describe_holder(now) if now else 'its lease was removed'} ({where})"
            )
        with _HELD_LOCK:
            _HELD.add(self.id)
        self._thread = threading.Thread(target=self._renew, name="covers-driver-lease", daemon=True)
        self._thread.start()
        return self

    def _renew(self) -> None:
        while not self._stop.wait(self.ttl_s / 3):
            try:
                now = self.read()
                if now is not None and now.get("id") != self.id:
                    self.lost = True
                    self.log(f"warning: the lease on this run was taken over by {describe_holder(now)}; stopping")
                    return
                self.record["renewals"] += 1
                self._write()
            except (OSError, StorageError) as e:  # the storage is away: the next renewal tries again
                self.log(f"warning: the run's lease could not be renewed ({type(e).__name__}: {e})")

    def check(self) -> None:
        """Raise :class:`LeaseHeld` if another driver took the lease over."""
        if self.lost:
            now = self.read()
            raise LeaseHeld(
                f"this driver lost the run's lease to {describe_holder(now) if now else 'another driver'}; "
                "it stops without writing on"
            )

    def release(self) -> None:
        """Stop renewing and remove the lease if it is still this driver's."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        with _HELD_LOCK:
            _HELD.discard(self.id)
        try:
            now = self.read()
            if now is not None and now.get("id") == self.id:
                self.storage.delete(LEASE)
        except (OSError, StorageError) as e:
            self.log(f"warning: the run's lease could not be removed ({type(e).__name__}: {e}); it expires by itself")
