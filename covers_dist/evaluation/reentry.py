"""What the other groups' training did to a group: its training episodes on either side of a gap.

In a stream of segments (``env.episodes_per_task`` episodes of one task group, then another group's),
each time a group comes back its first training episodes are acted by the policy it left, changed
only by what trained in between. With one policy per group (COVERS) nothing else trains it, so the
change across the gap is noise; with one shared network (Equi) the other groups' updates move it.
This module measures that change from a run's ``episodes.jsonl``, with no evaluation pass needed:

* a *segment* is a maximal run of consecutive episodes of one task;
* a *re-entry* of group ``t`` is a segment of ``t`` after an earlier segment of ``t`` (both with at
  least ``window`` episodes); ``before`` is the mean over the last ``window`` episodes of the earlier
  segment, ``after`` over the first ``window`` of the re-entry;
* per group: the number of re-entries, the mean ``before`` and ``after`` of the return and of the
  success, the mean change ``after - before`` of each with its standard error over the re-entries.

The episodes are the stochastic training episodes (not greedy evaluation ones), acted by the policy
the bank chose for them; a negative mean change beyond a few standard errors is forgetting within
the stream.

:func:`value_fit` reads the PPO updates' statistics in ``metrics.jsonl`` per group: an iteration's
row carries the statistics of the update of its own batch, or with ``runtime.pipeline`` of the
previous iteration's batch (docs/guide/runtime.md, "Pipelining"); the row names that batch
(``ppo/batch_iteration``; older logs: ``lag``), and a batch belongs to a group when all its
episodes are that group's. The median explained variance of the value function
over a group's updates says how well the critic fits that group's returns: a shared network's one
critic must fit every group at once. Plain Python + numpy.
"""

from __future__ import annotations

from typing import Any, Iterable, Sequence

import numpy as np

__all__ = ["reentry_changes", "segments", "value_fit"]


def segments(episodes: Iterable[dict[str, Any]]) -> list[tuple[str, list[dict[str, Any]]]]:
    """``(task, episodes)`` for every maximal run of consecutive episodes of one task, in the order
    of ``episode_index`` (a resumed run's repeated rows: the last one of each index is kept)."""
    by_index: dict[int, dict[str, Any]] = {}
    for e in episodes:
        if "episode_index" not in e or "task" not in e:
            raise ValueError(f"an episode row lacks episode_index or task: {sorted(e)}")
        by_index[int(e["episode_index"])] = e
    out: list[tuple[str, list[dict[str, Any]]]] = []
    for i in sorted(by_index):
        e = by_index[i]
        if out and out[-1][0] == e["task"]:
            out[-1][1].append(e)
        else:
            out.append((e["task"], [e]))
    return out


def _stat(values: Sequence[float]) -> dict[str, float]:
    xs = np.asarray(values, dtype=float)
    se = float(xs.std(ddof=1) / np.sqrt(xs.size)) if xs.size > 1 else float("nan")
    return {"mean": float(xs.mean()), "se": se}


def reentry_changes(episodes: Iterable[dict[str, Any]], window: int = 8) -> dict[str, dict[str, Any]]:
    """Per task: ``{"reentries", "return_before", "return_after", "return_change",
    "success_before", "success_after", "success_change"}`` (changes as ``{"mean", "se"}``) over every
    re-entry; tasks that never came back are left out. ``window`` episodes on either side."""
    if window < 1:
        raise ValueError(f"window must be >= 1 episode, got {window}")
    last: dict[str, list[dict[str, Any]]] = {}
    pairs: dict[str, list[tuple[float, float, float, float]]] = {}
    for task, eps in segments(episodes):
        if len(eps) < window:
            continue
        if task in last:
            before, after = last[task][-window:], eps[:window]
            pairs.setdefault(task, []).append(
                (
                    float(np.mean([e["return"] for e in before])),
                    float(np.mean([e["return"] for e in after])),
                    float(np.mean([e["success"] for e in before])),
                    float(np.mean([e["success"] for e in after])),
                )
            )
        last[task] = eps
    out: dict[str, dict[str, Any]] = {}
    for task, rows in pairs.items():
        a = np.asarray(rows, dtype=float)
        out[task] = {
            "reentries": int(a.shape[0]),
            "return_before": float(a[:, 0].mean()),
            "return_after": float(a[:, 1].mean()),
            "return_change": _stat(a[:, 1] - a[:, 0]),
            "success_before": float(a[:, 2].mean()),
            "success_after": float(a[:, 3].mean()),
            "success_change": _stat(a[:, 3] - a[:, 2]),
        }
    return out


def value_fit(
    metrics: Iterable[dict[str, Any]], episodes: Iterable[dict[str, Any]], lag: int = 1
) -> dict[str, dict[str, Any]]:
    """Per task: ``{"updates", "explained_variance"}``, the number of updates of batches of that task
    alone and the median of their ``ppo/explained_variance``. A row names the batch its update
    trained on (``ppo/batch_iteration``); logs written before rows did are read with ``lag``, the
    iterations between a batch and the row that reports its update (1 pipelined, 0 sequential).
    Rows repeated by a resume: the last."""
    if lag not in (0, 1):
        raise ValueError(f"lag must be 0 (sequential) or 1 (pipelined), got {lag}")
    tasks: dict[int, set[str]] = {}
    for e in episodes:
        if "iteration" in e:
            tasks.setdefault(int(e["iteration"]), set()).add(e["task"])
    rows = {int(m["iteration"]): m for m in metrics if "iteration" in m}
    values: dict[str, list[float]] = {}
    for it in sorted(rows):
        ev = rows[it].get("ppo/explained_variance")
        batch = tasks.get(int(rows[it].get("ppo/batch_iteration", it - lag)), set())
        if ev is None or not np.isfinite(ev) or len(batch) != 1:
            continue
        values.setdefault(next(iter(batch)), []).append(float(ev))
    return {t: {"updates": len(v), "explained_variance": float(np.median(v))} for t, v in values.items()}
