"""Continual-learning metrics over a run's evaluation passes (the Continual World definitions).

Wolczyk et al., "Continual World: A Robotic Benchmark For Continual Reinforcement Learning",
NeurIPS 2021, section 3 (docs/RESULTS.md gives the formulas with this project's choices):

* success ``p_i(t)`` of group ``i`` at pass ``t``: mean greedy success over the group's trainable
  (not held-out) ``(task, g)`` pairs, with the policy the bank picks (``agnostic``);
* average success ``A(t)``: mean of ``p_i(t)`` over the groups the stream has shown by ``t``;
* forgetting ``F_i``: the best success of group ``i`` at an earlier pass (after it was first seen)
  minus its success at the last pass (Continual World takes the success at the end of the
  group's own training; in a recurring stream a group has no single end, so the best earlier
  value is used); positive = forgotten;
* forward transfer ``FT_i = (AUC_i - AUC_i^ref) / (1 - AUC_i^ref)``: ``AUC`` is the normalised
  area under ``p_i`` over the env steps spent ON group ``i`` (so a group that recurs is measured
  on its own training time), ``ref`` a run that trained on group ``i`` alone, both up to the
  shorter of the two budgets;
* zero-shot success: mean greedy success over the held-out pairs (never trained on).
* worst-pair success of group ``i`` at pass ``t``: the lowest greedy success over all of its
  ``(task, g)`` pairs; a group is *held* at ``threshold`` when its worst pair meets it at ``held``
  consecutive passes (``eval.stop_at`` stops training on it, as ``bench learn``'s "solved").

An evaluation pass is the JSON object that ``eval.jsonl`` holds one per line (see
:mod:`covers_dist.evaluation.runner`). Plain Python + numpy.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from .stats import wilson_interval

__all__ = [
    "pair_success",
    "group_success",
    "group_worst",
    "held_groups",
    "groups_seen",
    "pass_summary",
    "forgetting",
    "forward_transfer",
    "continual_metrics",
    "metric_row",
]

TRAINABLE = ("seen", "unseen")


def _mean(values: Sequence[float]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def pair_success(row: dict[str, Any], key: str = "greedy/agnostic", field: str = "success") -> float | None:
    """One pair's figure (``success`` or ``return``) under ``mode/selection`` (None: not run)."""
    res = row.get("results", {}).get(key)
    return None if res is None else res.get(field)


def group_success(
    ev: dict[str, Any],
    task: str,
    key: str = "greedy/agnostic",
    statuses: Sequence[str] = TRAINABLE,
    field: str = "success",
) -> float | None:
    """Mean ``field`` of ``task``'s pairs whose status is in ``statuses`` at pass ``ev``."""
    return _mean([pair_success(r, key, field) for r in ev["pairs"] if r["task"] == task and r["status"] in statuses])


def group_worst(ev: dict[str, Any], task: str, key: str = "greedy/agnostic") -> float | None:
    """Lowest success over every ``(task, g)`` pair of ``task`` at pass ``ev``, held-out and unseen pairs
    included: "solved on every transform" is judged by it (None: no pair ran)."""
    values = [pair_success(r, key) for r in ev["pairs"] if r["task"] == task]
    values = [v for v in values if v is not None]
    return float(min(values)) if values else None


def held_groups(passes: Sequence[dict[str, Any]], threshold: float, held: int, key: str = "greedy/agnostic") -> list[str]:
    """Tasks whose worst pair (:func:`group_worst`) is >= ``threshold`` at each of the last ``held``
    passes (oldest first), in the order of the last pass's pairs; [] before ``held`` passes."""
    if held < 1:
        raise ValueError(f"held={held} must be >= 1")
    if len(passes) < held:
        return []
    last = passes[-held:]
    tasks = dict.fromkeys(r["task"] for r in last[-1]["pairs"])

    def meets(ev: dict[str, Any], task: str) -> bool:
        worst = group_worst(ev, task, key)
        return worst is not None and worst >= threshold

    return [t for t in tasks if all(meets(ev, t) for ev in last)]


def group_counts(
    ev: dict[str, Any], task: str, key: str = "greedy/agnostic", statuses: Sequence[str] = TRAINABLE
) -> dict[str, Any] | None:
    """``task``'s successes pooled over its pairs at pass ``ev``: ``{"successes", "n", "ci95"}``
    (Wilson 95%); None when no pair ran or the pass predates the counts."""
    results = [r["results"].get(key) for r in ev["pairs"] if r["task"] == task and r["status"] in statuses]
    results = [res for res in results if res is not None]
    if not results or not all("successes" in res and "n" in res for res in results):
        return None
    k, n = sum(int(res["successes"]) for res in results), sum(int(res["n"]) for res in results)
    lo, hi = wilson_interval(k, n)
    return {"successes": k, "n": n, "ci95": [round(lo, 4), round(hi, 4)]}


def groups_seen(ev: dict[str, Any]) -> list[str]:
    """Tasks the stream had shown when pass ``ev`` ran."""
    return [t for t, info in ev.get("groups", {}).items() if info.get("first_episode") is not None]


def pass_summary(ev: dict[str, Any]) -> dict[str, Any]:
    """Per group (success, seen/held-out/oracle success, return) and the pass's averages."""
    tasks = list(dict.fromkeys(r["task"] for r in ev["pairs"]))
    per = {}
    for t in tasks:
        per[t] = {
            "success": group_success(ev, t),
            "success_worst": group_worst(ev, t),
            "success_seen": group_success(ev, t, statuses=("seen",)),
            "success_held_out": group_success(ev, t, statuses=("held_out",)),
            "success_oracle": group_success(ev, t, key="greedy/oracle"),
            "success_stochastic": group_success(ev, t, key="stochastic/agnostic"),
            "return": group_success(ev, t, field="return"),
            "success_counts": group_counts(ev, t),
        }
    seen = [t for t in groups_seen(ev) if t in per]
    held = [pair_success(r) for r in ev["pairs"] if r["status"] == "held_out"]
    return {
        "groups": per,
        "average_success": _mean([per[t]["success"] for t in seen]),
        "zero_shot_success": _mean(held),
    }


def forgetting(passes: Sequence[dict[str, Any]], task: str) -> float | None:
    """Best success of ``task`` at a pass before the last (after it was first seen) minus the last."""
    curve = [group_success(ev, task) for ev in passes if task in groups_seen(ev)]
    curve = [c for c in curve if c is not None]
    if len(curve) < 2:
        return None
    return float(max(curve[:-1]) - curve[-1])


def _curve(passes: Sequence[dict[str, Any]], task: str) -> tuple[np.ndarray, np.ndarray]:
    """(env steps spent on ``task``, its success) at every pass that has both, sorted by steps."""
    pts = []
    for ev in passes:
        steps = ev.get("groups", {}).get(task, {}).get("env_steps")
        succ = group_success(ev, task)
        if steps is not None and succ is not None:
            pts.append((float(steps), succ))
    pts.sort(key=lambda p: p[0])  # stable: passes at equal steps (group not trained between) stay in time order
    return np.array([p[0] for p in pts]), np.array([p[1] for p in pts])


def _auc(steps: np.ndarray, success: np.ndarray, budget: float) -> float | None:
    """Normalised area under the success curve over [0, budget] (the first value held back to 0)."""
    if budget <= 0 or len(steps) == 0:
        return None
    x = np.concatenate([[0.0], steps[steps <= budget]])
    y = np.concatenate([[success[0]], success[steps <= budget]])
    if x[-1] < budget:  # hold the last value to the end of the budget
        x, y = np.append(x, budget), np.append(y, y[-1])
    return float(np.sum((x[1:] - x[:-1]) * (y[1:] + y[:-1]) / 2.0) / budget)


def forward_transfer(passes: Sequence[dict[str, Any]], task: str, reference: Sequence[dict[str, Any]]) -> float | None:
    """``(AUC - AUC_ref) / (1 - AUC_ref)`` of ``task`` against a single-group ``reference`` run's passes."""
    xs, ys = _curve(passes, task)
    xr, yr = _curve(reference, task)
    if len(xs) == 0 or len(xr) == 0:
        return None
    budget = min(xs[-1], xr[-1])
    auc, ref = _auc(xs, ys, budget), _auc(xr, yr, budget)
    if auc is None or ref is None:
        return None
    if ref >= 1.0:
        return 0.0 if auc >= 1.0 else float(auc - ref)
    return float((auc - ref) / (1.0 - ref))


def continual_metrics(
    passes: Sequence[dict[str, Any]], references: dict[str, Sequence[dict[str, Any]]] | None = None
) -> dict[str, Any]:
    """Everything above for a run's passes (oldest first); ``references``: {task: reference passes}."""
    if not passes:
        raise ValueError("no evaluation passes: run `covers-dist eval RUN_DIR` or train with eval.every_iterations > 0")
    last = passes[-1]
    summary = pass_summary(last)
    tasks = list(summary["groups"])
    forg = {t: forgetting(passes, t) for t in tasks}
    ft = {t: forward_transfer(passes, t, ref) for t, ref in (references or {}).items() if t in tasks}
    return {
        "iteration": last.get("iteration"),
        "env_steps": last.get("env_steps"),
        "passes": len(passes),
        **summary,
        "forgetting": forg,
        "average_forgetting": _mean([v for v in forg.values() if v is not None]),
        "forward_transfer": ft,
        "average_forward_transfer": _mean([v for v in ft.values() if v is not None]),
    }


def metric_row(cl: dict[str, Any], prefix: str = "eval") -> dict[str, float]:
    """Flat scalars (``eval/average_success``, ``eval/success/<task>``, ...) for metrics.jsonl,
    TensorBoard and the HTTP service; entries without a value are left out."""
    row: dict[str, float] = {}
    for name in ("average_success", "zero_shot_success", "average_forgetting", "average_forward_transfer"):
        if cl.get(name) is not None:
            row[f"{prefix}/{name}"] = float(cl[name])
    for task, g in cl["groups"].items():
        for name in ("success", "success_worst", "success_held_out", "success_oracle", "return"):
            if g.get(name) is not None:
                row[f"{prefix}/{name}/{task}"] = float(g[name])
    for name in ("forgetting", "forward_transfer"):
        for task, v in cl.get(name, {}).items():
            if v is not None:
                row[f"{prefix}/{name}/{task}"] = float(v)
    return row
