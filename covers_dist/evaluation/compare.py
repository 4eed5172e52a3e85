"""Methods side by side: the evaluation results of several runs of one stream, one row per run.

The COVERS paper's Table 1 compares COVERS with its baselines (CNN, Equi, COVERS-GT, COVERS-CNN)
on one stream; here each method is its own run directory (``runtime.method``), and this module puts
their latest evaluation passes in one table: per task group success over its trainable ``(task, g)``
pairs (policy chosen by the bank), the average over groups, zero-shot success on the held-out pairs,
average forgetting, policies and ARI, and the env steps each run had.

Runs are compared only when they share what decides a success: the suite, the task groups, the
symmetry group, the episode length and the held-out pairs. :func:`check_comparable` names the first
field that differs. Plain Python + numpy (:mod:`covers_dist.commands.compare` loads the runs and
draws the curves).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

from .metrics import continual_metrics, group_success, pass_summary
from .report import PAPER_AVERAGE, PAPER_SUCCESS, _f, markdown_table

__all__ = ["RunResults", "check_comparable", "compare_table", "comparison_json", "run_label", "success_curve"]


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

    @property
    def held_out(self) -> list[tuple[str, str]]:
        """The (task, g) pairs of the latest pass that were held out of training."""
        return sorted((r["task"], r["g"]) for r in self.passes[-1]["pairs"] if r["status"] == "held_out")

    def metrics(self) -> dict[str, Any]:
        return continual_metrics(self.passes)


def run_label(method: str, name: str, taken: Sequence[str]) -> str:
    """``method``, or ``method (name)`` when another run already uses that label."""
    return method if method not in taken else f"{method} ({name})"


def check_comparable(runs: Sequence[RunResults]) -> None:
    """Raise ``ValueError`` naming the first field in which a run differs from the first run."""
    if len(runs) < 1:
        raise ValueError("nothing to compare: give at least one run directory")
    for r in runs:
        if not r.passes:
            raise ValueError(f"{r.path} holds no evaluation pass: run `covers-dist eval {r.path}`")
    ref = runs[0]
    for r in runs[1:]:
        for field in ("suite", "tasks", "group", "max_episode_steps", "held_out"):
            a, b = getattr(ref, field), getattr(r, field)
            if a != b:
                raise ValueError(
                    f"{r.path} is not comparable with {ref.path}: {field} is {b!r} there and {a!r} here "
                    "(compare runs of one stream: same suite, tasks, group, episode length and held-out pairs)"
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
    }


def comparison_json(runs: Sequence[RunResults]) -> dict[str, Any]:
    """The table's content as plain data (``--json``)."""
    check_comparable(runs)
    ref = runs[0]
    return {
        "suite": ref.suite,
        "tasks": list(ref.tasks),
        "group": ref.group,
        "held_out": [list(p) for p in ref.held_out],
        "runs": [_row(r) for r in runs],
    }


def _ari(row: dict[str, Any], tasks: Sequence[str]) -> str:
    """The ARI cell; one policy for several groups has ARI 0 by definition, which says nothing."""
    return "n/a (one policy)" if row["policies"] == 1 and len(tasks) > 1 else _f(row["ari"])


def compare_table(data: dict[str, Any], paper: bool = True) -> str:
    """A Markdown table of :func:`comparison_json`'s ``data``: one row per run (and the paper's COVERS
    row when the tasks are the paper's)."""
    tasks = data["tasks"]
    names = [PAPER_SUCCESS.get(t, (t,))[0] for t in tasks]
    header = ["method", "seed", "env steps"] + names
    header += ["average", "held-out (zero-shot)", "forgetting", "policies", "ARI"]
    rows = []
    for r in data["runs"]:
        rows.append(
            [r["label"], str(r["seed"]), str(r["env_steps"])]
            + [r["success"].get(t) for t in tasks]
            + [r["average_success"], r["zero_shot_success"], r["average_forgetting"], str(r["policies"]), _ari(r, tasks)]
        )
    if paper and all(t in PAPER_SUCCESS for t in tasks):
        rows.append(
            ["COVERS, paper (3 seeds, ~3M steps per group)", "", ""]
            + [f"{PAPER_SUCCESS[t][1]:.2f} +- {PAPER_SUCCESS[t][2]:.2f}" for t in tasks]
            + [f"{PAPER_AVERAGE[0]:.2f} +- {PAPER_AVERAGE[1]:.2f}", "n/a", "n/a", "n/a", "n/a"]
        )
    return markdown_table(header, rows)
