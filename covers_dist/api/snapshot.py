"""A periodically refreshed snapshot of the clustering state, served by the GET endpoints.

Reading the clustering actor on every request would put each request in the actor's queue
behind the training run's own assignment calls (slow answers while it computes distances) and
the training run behind the requests. Instead one background thread reads the state every
``api.refresh_s`` seconds (the bank summary, the latest record, the metrics, and the new part of
the assignment history, all in one round trip) and the endpoints answer from memory. Every
answer carries ``as_of``, the time its snapshot was read.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from .sources import Source

__all__ = ["Snapshot", "SnapshotCache", "json_safe"]

log = logging.getLogger("covers_dist.api")

HISTORY_PAGE = 1000
RATE_WINDOW_S = 30.0


def json_safe(x: Any) -> Any:
    """``x`` with every non-finite float replaced by None (JSON has no NaN or infinity)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    return x


@dataclass
class Snapshot:
    """The clustering state at one moment."""

    summary: dict[str, Any]
    last: dict[str, Any] | None
    metrics: dict[str, Any]
    history: Sequence[dict[str, Any]] = field(default_factory=list)  # a HistoryView of the cache
    as_of: float = 0.0
    env_steps_per_s: float | None = None
    per_task: dict[str, Any] = field(default_factory=dict)  # latest success/<task>, return/<task> seen
    rendered: dict[str, bytes] = field(default_factory=dict)  # JSON answers built from this snapshot

    @property
    def policies(self) -> dict[int, dict[str, Any]]:
        return {int(p["policy_id"]): p for p in self.summary.get("policies", [])}


class HistoryView(Sequence):
    """The first ``n`` records of the cache's history list, without copying it: a snapshot costs the
    same however long the history (the list only grows; a restarted service gets a new list)."""

    def __init__(self, items: list[dict[str, Any]], n: int) -> None:
        self._items, self._n = items, min(int(n), len(items))

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, index: Any) -> Any:
        if isinstance(index, slice):
            start, stop, step = index.indices(self._n)
            return self._items[start:stop:step]
        i = index + self._n if index < 0 else index
        if not 0 <= i < self._n:
            raise IndexError(index)
        return self._items[i]


class SnapshotCache:
    """Keeps the latest :class:`Snapshot` of ``source``; :meth:`start` refreshes it in a thread."""

    def __init__(self, source: Source, refresh_s: float = 0.5) -> None:
        self.source = source
        self.refresh_s = float(refresh_s)
        self.latest: Snapshot | None = None
        self.last_error: str | None = None
        self.refreshes = 0
        self._history: list[dict[str, Any]] = []
        self._steps: deque[tuple[float, float]] = deque()  # (wall time, env steps) of progress rows
        self._per_task: dict[str, Any] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def refresh(self) -> Snapshot:
        """Read the state now (one round trip, plus one per 1000 new history records)."""
        with self._lock:
            summary, last, metrics = self.source.call_many(["summary", "last_assignment", "metrics"])
            total = int(summary.get("assignments", 0))
            if total < len(self._history):  # a restarted service with less history: start over
                self._history = []
            while len(self._history) < total:
                page = self.source.call("assignments", len(self._history), HISTORY_PAGE)
                if not page:
                    break
                self._history.extend(json_safe(r) for r in page)
            metrics = json_safe(metrics)
            snap = Snapshot(json_safe(summary), json_safe(last), metrics, HistoryView(self._history, total), time.time())
            progress = metrics.get("progress") or {}
            snap.env_steps_per_s = self._rate(progress)
            self._per_task.update((k, v) for k, v in progress.items() if k.startswith(("success/", "return/")))
            snap.per_task = dict(self._per_task)
            self.latest = snap
            self.last_error = None
            self.refreshes += 1
            return snap

    def _rate(self, progress: dict[str, Any]) -> float | None:
        """Env steps/s: the driver's own figure, else measured over the last progress rows."""
        if isinstance(progress.get("env_steps_per_s"), (int, float)):
            return float(progress["env_steps_per_s"])
        t, steps = progress.get("wall_time"), progress.get("env_steps")
        if not isinstance(t, (int, float)) or not isinstance(steps, (int, float)):
            return None
        if self._steps and (t < self._steps[-1][0] or steps < self._steps[-1][1]):
            self._steps.clear()  # a new or resumed run
            self._per_task.clear()
        if not self._steps or t > self._steps[-1][0]:
            self._steps.append((float(t), float(steps)))
        while len(self._steps) > 2 and t - self._steps[1][0] >= RATE_WINDOW_S:
            self._steps.popleft()
        (t0, s0), (t1, s1) = self._steps[0], self._steps[-1]
        return (s1 - s0) / (t1 - t0) if t1 > t0 else None

    def _run(self) -> None:
        while not self._stop.wait(self.refresh_s):
            try:
                self.refresh()
            except Exception as e:  # noqa: BLE001 - keep serving the last snapshot, report in /readyz
                msg = f"{type(e).__name__}: {e}"
                if msg != self.last_error:
                    log.warning("refreshing the clustering snapshot failed: %s", msg)
                self.last_error = msg

    def start(self) -> None:
        """Take a first snapshot (errors are kept for /readyz) and refresh in the background."""
        try:
            self.refresh()
        except Exception as e:  # noqa: BLE001
            self.last_error = f"{type(e).__name__}: {e}"
        self._thread = threading.Thread(target=self._run, name="covers-api-snapshot", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.source.timeout_s + 1.0)

    def age_s(self) -> float | None:
        return None if self.latest is None else time.time() - self.latest.as_of
