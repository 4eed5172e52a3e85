"""Methods side by side: the evaluation results of several runs of one stream, one row per run.

The COVERS paper's Table 1 compares COVERS with its baselines (CNN, Equi, COVERS-GT, COVERS-CNN)
on one stream; here each method is its own run directory (``runtime.method``), and this module puts
their latest evaluation passes in one table: per task group success over its trainable ``(task, g)``
pairs (policy chosen by the bank), the average over groups, zero-shot success on the held-out pairs,
average forgetting, policies and ARI, and the env steps each run had.

Runs are compared only when they share what decides a success: the suite, the task groups, the
symmetry group, the episode length and the held-out pairs. :func:`check_comparable` names the first
field that differs. Seeds of one stream draw different held-out pairs, so runs of several seeds are
compared with ``across_seeds``: each run's held-out column is then its own pairs' zero-shot success,
and :func:`aggregate_by_method` adds one row per method, the mean and standard deviation over its
seeds (as the paper reports its 3 seeds). Plain Python + numpy (:mod:`covers_dist.commands.compare`
loads the runs and draws the curves).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .metrics import continual_metrics, group_success, pass_summary
from .report import PAPER_AVERAGE, PAPER_SUCCESS, _f, group_name, markdown_table

__all__ = [
    "RunResults",
    "aggregate_by_method",
    "check_comparable",
    "compare_table",
    "comparison_json",
    "methods_table",
    "reentry_table",
    "run_labels",
    "success_curve",
    "value_fit_table",
]


@dataclass
class RunResults:
    """One run's evaluation passes (oldest first), its config fields and its bank's metrics."""

    path: str
    method: str
    seed: int
    suite: str
    tasks: list[str]
    group: str
    max_episode_steps: int
    passes: list[dict[str, Any]]
    bank: dict[str, Any]
    label: str = ""
    #: :func:`~covers_dist.evaluation.reentry.reentry_changes` of its training episodes (None: no log)
    reentry: dict[str, Any] | None = None
    #: :func:`~covers_dist.evaluation.reentry.value_fit` of its updates (None: no log)
    value_fit: dict[str, Any] | None = None

    @property
    def held_out(self) -> list[tuple[str, str]]:
        """The (task, g) pairs of the latest pass that were held out of training."""
        return sorted((r["task"], r["g"]) for r in self.passes[-1]["pairs"] if r["status"] == "held_out")

    def metrics(self) -> dict[str, Any]:
        return continual_metrics(self.passes)


def run_labels(runs: Sequence[RunResults]) -> list[str]:
    """Each run's name in tables and figures: its method; ``method seed S`` where the method has
    several runs; ``method (directory)`` where one method has several runs of one seed."""
    methods = Counter(r.method for r in runs)
    seeds = Counter((r.method, r.seed) for r in runs)
    labels = []
    for r in runs:
        if methods[r.method] == 1:
            labels.append(r.method)
        elif seeds[(r.method, r.seed)] == 1:
            labels.append(f"{r.method} seed {r.seed}")
        else:
            labels.append(f"{r.method} ({Path(r.path).name})")
    return labels


def check_comparable(runs: Sequence[RunResults], across_seeds: bool = False) -> None:
    """Raise ``ValueError`` naming the first field in which a run differs from the first run
    (``across_seeds``: the held-out pairs may differ)."""
    if len(runs) < 1:
        raise ValueError("nothing to compare: give at least one run directory")
    for r in runs:
        if not r.passes:
            raise ValueError(f"{r.path} holds no evaluation pass: run `covers-dist eval {r.path}`")
    ref = runs[0]
    fields = ("suite", "tasks", "group", "max_episode_steps") + (() if across_seeds else ("held_out",))
    for r in runs[1:]:
        for field in fields:
            a, b = getattr(ref, field), getattr(r, field)
            if a != b:
                hint = "" if across_seeds or field != "held_out" else "; runs of different seeds: --across-seeds"
                raise ValueError(
                    f"{r.path} is not comparable with {ref.path}: {field} is {b!r} there and {a!r} here "
                    f"(compare runs of one stream: same suite, tasks, group, episode length and held-out pairs{hint})"
                )


def success_curve(run: RunResults, task: str | None = None) -> tuple[list[float], list[float | None]]:
    """(env steps, success) at every pass: one group's (``task``) or the average over groups seen."""
    steps, values = [], []
    for ev in run.passes:
        steps.append(float(ev.get("env_steps") or 0))
        values.append(pass_summary(ev)["average_success"] if task is None else group_success(ev, task))
    return steps, values


def _row(run: RunResults) -> dict[str, Any]:
    cl = run.metrics()
    return {
        "label": run.label or run.method,
        "method": run.method,
        "seed": run.seed,
        "run_dir": run.path,
        "env_steps": cl["env_steps"],
        "iteration": cl["iteration"],
        "passes": cl["passes"],
        "success": {t: g["success"] for t, g in cl["groups"].items()},
        "average_success": cl["average_success"],
        "zero_shot_success": cl["zero_shot_success"],
        "average_forgetting": cl["average_forgetting"],
        "policies": int(run.bank.get("num_policies", 0)),
        "ari": run.bank.get("ari"),
        "held_out": [list(p) for p in run.held_out],
        "reentry": run.reentry,
        "value_fit": run.value_fit,
    }


def _mean_std(values: Sequence[Any]) -> dict[str, Any] | None:
    """``{"mean", "std", "n"}`` of the values that exist (std with ddof 1; 0.0 for one value)."""
    xs = np.array([float(v) for v in values if v is not None], dtype=float)
    if xs.size == 0:
        return None
    return {"mean": float(xs.mean()), "std": float(xs.std(ddof=1)) if xs.size > 1 else 0.0, "n": int(xs.size)}


def aggregate_by_method(rows: Sequence[dict[str, Any]], tasks: Sequence[str]) -> list[dict[str, Any]]:
    """One entry per method (in order of first appearance): the mean and standard deviation over its
    runs of every column of the table. A method given twice with one seed is refused (it would count
    one seed twice)."""
    by_method: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        same = [o for o in by_method.get(r["method"], []) if o["seed"] == r["seed"]]
        if same:
            raise ValueError(
                f"{r['run_dir']} and {same[0]['run_dir']} are both {r['method']} with seed {r['seed']}: "
                "averaging over seeds needs one run per method and seed"
            )
        by_method.setdefault(r["method"], []).append(r)
    out = []
    for method, rs in by_method.items():
        col = lambda key: _mean_std([r[key] for r in rs])  # noqa: E731
        out.append(
            {
                "method": method,
                "seeds": [r["seed"] for r in rs],
                "env_steps": col("env_steps"),
                "success": {t: _mean_std([r["success"].get(t) for r in rs]) for t in tasks},
                "average_success": col("average_success"),
                "zero_shot_success": col("zero_shot_success"),
                "average_forgetting": col("average_forgetting"),
                "policies": col("policies"),
                "ari": col("ari"),
            }
        )
    return out


def comparison_json(runs: Sequence[RunResults], across_seeds: bool = False) -> dict[str, Any]:
    """The table's content as plain data (``--json``). With ``across_seeds`` the runs may hold out
    different pairs (each row lists its own; the top-level ``held_out`` is then null) and
    ``methods`` holds :func:`aggregate_by_method`'s rows."""
    check_comparable(runs, across_seeds=across_seeds)
    ref = runs[0]
    rows = [_row(r) for r in runs]
    same = all(r.held_out == ref.held_out for r in runs)
    data = {
        "suite": ref.suite,
        "tasks": list(ref.tasks),
        "group": ref.group,
        "held_out": [list(p) for p in ref.held_out] if same else None,
        "runs": rows,
    }
    if across_seeds:
        data["methods"] = aggregate_by_method(rows, ref.tasks)
    return data


def _ari(row: dict[str, Any], tasks: Sequence[str]) -> str:
    """The ARI cell; one policy for several groups has ARI 0 by definition, which says nothing."""
    return "n/a (one policy)" if row["policies"] == 1 and len(tasks) > 1 else _f(row["ari"])


def _pm(stat: dict[str, Any] | None) -> str:
    return "n/a" if stat is None else f"{stat['mean']:.2f} +- {stat['std']:.2f}"


def _paper_row(tasks: Sequence[str], lead: Sequence[str]) -> list[Any]:
    return (
        [*lead]
        + [f"{PAPER_SUCCESS[t][1]:.2f} +- {PAPER_SUCCESS[t][2]:.2f}" for t in tasks]
        + [f"{PAPER_AVERAGE[0]:.2f} +- {PAPER_AVERAGE[1]:.2f}", "n/a", "n/a", "n/a", "n/a"]
    )


def _header(tasks: Sequence[str], lead: Sequence[str]) -> list[str]:
    names = [group_name(t) for t in tasks]
    return [*lead, *names, "average", "held-out (zero-shot)", "forgetting", "policies", "ARI"]


def methods_table(data: dict[str, Any], paper: bool = True) -> str:
    """A Markdown table of ``data["methods"]`` (:func:`comparison_json` with ``across_seeds``): one
    row per method, mean +- standard deviation over its seeds (and the paper's COVERS row)."""
    tasks = data["tasks"]
    header = _header(tasks, ["method", "seeds", "env steps (mean)"])
    rows = []
    for m in data["methods"]:
        one_policy = m["policies"] is not None and m["policies"]["mean"] == 1 and len(tasks) > 1
        rows.append(
            [m["method"], ", ".join(str(s) for s in m["seeds"]), f"{m['env_steps']['mean']:.0f}"]
            + [_pm(m["success"].get(t)) for t in tasks]
            + [_pm(m[k]) for k in ("average_success", "zero_shot_success", "average_forgetting", "policies")]
            + ["n/a (one policy)" if one_policy else _pm(m["ari"])]
        )
    if paper and all(t in PAPER_SUCCESS for t in tasks):
        rows.append(_paper_row(tasks, ["COVERS, paper (~3M steps per group)", "3 seeds", ""]))
    return markdown_table(header, rows)


def compare_table(data: dict[str, Any], paper: bool = True) -> str:
    """A Markdown table of :func:`comparison_json`'s ``data``: one row per run (and the paper's COVERS
    row when the tasks are the paper's)."""
    tasks = data["tasks"]
    header = _header(tasks, ["method", "seed", "env steps"])
    rows = []
    for r in data["runs"]:
        rows.append(
            [r["label"], str(r["seed"]), str(r["env_steps"])]
            + [r["success"].get(t) for t in tasks]
            + [r["average_success"], r["zero_shot_success"], r["average_forgetting"], str(r["policies"]), _ari(r, tasks)]
        )
    if paper and all(t in PAPER_SUCCESS for t in tasks):
        rows.append(_paper_row(tasks, ["COVERS, paper (3 seeds, ~3M steps per group)", "", ""]))
    return markdown_table(header, rows)


def reentry_table(data: dict[str, Any]) -> str | None:
    """A Markdown table of each run's re-entry changes (:mod:`covers_dist.evaluation.reentry`): per
    group, the mean training return over the last episodes before a gap -> the first after it, the
    mean change +- its standard error, and the success before -> after; None when no run has them."""
    tasks = data["tasks"]
    if not any(r.get("reentry") for r in data["runs"]):
        return None
    header = ["method", "seed", *[group_name(t) for t in tasks]]
    rows = []
    for r in data["runs"]:
        cells = []
        for t in tasks:
            x = (r.get("reentry") or {}).get(t)
            if x is None:
                cells.append("n/a")
                continue
            ch = x["return_change"]
            cells.append(
                f"{x['return_before']:.0f} -> {x['return_after']:.0f} ({ch['mean']:+.0f} +- {ch['se']:.0f}); "
                f"success {x['success_before']:.2f} -> {x['success_after']:.2f}; n={x['reentries']}"
            )
        rows.append([r["label"], str(r["seed"]), *cells])
    return markdown_table(header, rows)


def value_fit_table(data: dict[str, Any]) -> str | None:
    """A Markdown table of each run's value fit per group (``0.93 (n=156)``); None when no run has it."""
    tasks = data["tasks"]
    if not any(r.get("value_fit") for r in data["runs"]):
        return None
    rows = []
    for r in data["runs"]:
        fit = r.get("value_fit") or {}
        cells = [
            "n/a" if fit.get(t) is None else f"{fit[t]['explained_variance']:.2f} (n={fit[t]['updates']})" for t in tasks
        ]
        rows.append([r["label"], str(r["seed"]), *cells])
    return markdown_table(["method", "seed", *[group_name(t) for t in tasks]], rows)
