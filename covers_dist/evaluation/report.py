"""Tables of evaluation results: the per-pair grid of one pass and the paper-layout results table.

Plain Python; ``covers-dist eval`` prints them, ``covers-dist report`` writes them into
``RUN_DIR/report.md`` (docs/RESULTS.md explains how to read it).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np


__all__ = [
    "PAPER_SUCCESS",
    "PAPER_AVERAGE",
    "calibration_tail_section",
    "group_name",
    "pairs_table",
    "passes_table",
    "results_table",
    "markdown_table",
]

#: COVERS paper (CoRL 2023), success rate per task group, mean +- 95% CI over 3 seeds.
PAPER_SUCCESS: dict[str, tuple[str, float, float]] = {
    "plate-slide-v3": ("Plate Slide", 0.95, 0.04),
    "button-press-topdown-v3": ("Button Press", 0.88, 0.06),
    "drawer-close-v3": ("Drawer Close", 0.91, 0.05),
    "reach-v3": ("Goal Reach", 0.95, 0.04),
}
PAPER_AVERAGE: tuple[float, float] = (0.94, 0.02)


def group_name(task: str) -> str:
    """The paper's name of a task group (``Goal Reach`` for ``reach-v3``), else the task itself."""
    return PAPER_SUCCESS.get(task, (task,))[0]


def _f(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return str(int(v))
    return f"{float(v):.{digits}f}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table (cells are formatted with :func:`_f` unless strings)."""
    cells = [[c if isinstance(c, str) else _f(c) for c in r] for r in rows]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in cells]
    return "\n".join(lines)


def pairs_table(ev: dict[str, Any]) -> str:
    """Every (task, g) of one pass: status, chosen policies, success per mode/selection and, where
    the env reports how close episodes came, the failures' median closest approach in success radii
    and how many were near misses (within :data:`~covers_dist.evaluation.stats.NEAR_MISS`)."""
    keys = [f"{m}/{s}" for m in ev.get("modes", ["greedy"]) for s in ev.get("selections", ["agnostic"])]
    header = ["task", "g", "status", "agnostic policy (decision)", "oracle policy"] + [f"success {k}" for k in keys]
    misses = any("misses" in res for r in ev["pairs"] for res in r.get("results", {}).values())
    if misses:  # the env reports how close episodes came: how far the failures stayed
        header += [f"misses {k}" for k in keys]
    rows = []
    for r in ev["pairs"]:
        choice = "n/a" if r.get("agnostic_policy") is None else f"{r['agnostic_policy']} ({r.get('agnostic_decision')})"
        oracle = "n/a" if r.get("oracle_policy") is None else str(r["oracle_policy"])
        results = r.get("results", {})
        row = [r["task"], r["g"], r["status"], choice, oracle] + [_with_n(results.get(k)) for k in keys]
        rows.append(row + ([_misses(results.get(k)) for k in keys] if misses else []))
    return markdown_table(header, rows)


def _misses(res: dict[str, Any] | None) -> str:
    """A pair's failed episodes and how close they came, ``2 at 1.12 radii (2 near)``, or ``-``."""
    if not res or "misses" not in res:
        return "-"
    return f"{res['misses']} at {_f(res['misses_closest_median'])} radii ({res['near_misses']} near)"


def _steps(n: Any) -> str:
    """Env steps as a column head: 240k, 1.44M."""
    n = float(n or 0)
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.4g}k"


def passes_table(passes: Sequence[dict[str, Any]], tasks: Sequence[str]) -> str:
    """Each group's greedy success at every pass, ``mean/worst``: the mean over its trainable pairs
    and the lowest over all its pairs (held-out ones included), policy chosen by the bank; ``-``
    before the stream showed the group. One column per pass, oldest first."""
    from .metrics import group_success, group_worst

    header = ["group", *[_steps(ev.get("env_steps")) for ev in passes]]
    rows = []
    for t in tasks:
        cells = []
        for ev in passes:
            mean, worst = group_success(ev, t), group_worst(ev, t)
            cells.append("-" if mean is None and worst is None else f"{_f(mean)}/{_f(worst)}")
        rows.append([group_name(t), *cells])
    return markdown_table(header, rows)


def _with_n(res: dict[str, Any] | None) -> Any:
    """A pair's success with the episodes behind it, ``0.62 (5/8)`` (older passes: the rate alone)."""
    if res is None:
        return None
    if "successes" in res and "n" in res:
        return f"{_f(res['success'])} ({res['successes']}/{res['n']})"
    return res.get("success")


def _policies_per_group(confusion: dict[str, Any]) -> dict[int, tuple[int, float | None]]:
    """{group id: (policies that served it, share of its episodes on its main policy)}."""
    policies, groups = confusion.get("policies", []), confusion.get("groups", [])
    out: dict[int, tuple[int, float | None]] = {}
    if not policies or not groups:
        return out
    table = np.asarray(confusion.get("counts", []), dtype=float).reshape(len(policies), len(groups))
    for j, gid in enumerate(groups):
        col = table[:, j]
        out[int(gid)] = (int((col > 0).sum()), float(col.max() / col.sum()) if col.sum() else None)
    return out


def results_table(cl: dict[str, Any], bank_metrics: dict[str, Any], tasks: Sequence[str]) -> str:
    """The paper-layout table: one row per task group and an average row, ours beside the paper's."""
    per_group = _policies_per_group(bank_metrics.get("confusion") or {})
    header = [
        "task group",
        "success seen",
        "success held-out",
        "success (all trainable g)",
        "oracle success",
        "return",
        "policies",
        "episodes on main policy",
        "forgetting",
        "paper success",
    ]
    rows = []
    for gid, task in enumerate(tasks):
        g = cl["groups"].get(task)
        if g is None:
            continue
        label, paper, ci = PAPER_SUCCESS.get(task, (task, None, None))
        n_pol, purity = per_group.get(gid, (0, None))
        rows.append(
            [
                label if label == task else f"{label} ({task})",
                g["success_seen"],
                g["success_held_out"],
                g["success"],
                g["success_oracle"],
                g["return"],
                n_pol,
                purity,
                cl["forgetting"].get(task),
                "n/a" if paper is None else f"{paper:.2f} +- {ci:.2f}",
            ]
        )
    paper_avg = all(t in PAPER_SUCCESS for t in tasks) and len(tasks) == len(PAPER_SUCCESS)
    rows.append(
        [
            "**average**",
            _avg(cl, "success_seen"),
            cl.get("zero_shot_success"),
            cl.get("average_success"),
            _avg(cl, "success_oracle"),
            _avg(cl, "return"),
            int(bank_metrics.get("num_policies", 0)),
            f"ARI {_f(bank_metrics.get('ari'))}",
            cl.get("average_forgetting"),
            f"{PAPER_AVERAGE[0]:.2f} +- {PAPER_AVERAGE[1]:.2f}" if paper_avg else "n/a",
        ]
    )
    return markdown_table(header, rows)


def _avg(cl: dict[str, Any], name: str) -> float | None:
    vals = [g[name] for g in cl["groups"].values() if g.get(name) is not None]
    return float(np.mean(vals)) if vals else None


def calibration_tail_section(tail: dict[str, Any] | None) -> list[str]:
    """Report lines for :func:`~covers_dist.clustering.calibration_tail` (none without a
    calibrated record)."""
    if not tail:
        return []
    rows = []
    for row in tail["rows"]:
        ratio = row["count"] / row["expected"] if row["expected"] else None
        rows.append([row["k"], row["count"], f"{row['expected']:.2f}", "n/a" if ratio is None else f"{ratio:.2f}"])
    splits = (
        f"{tail['false_splits']} false split(s) (a new policy for a group that had one)"
        if tail["labelled"]
        else "false splits unknown (no true group ids)"
    )
    return [
        "",
        f"## The calibrated rule's tail (false-split rate {tail['false_split_rate']:g}, N = {tail['max_draws']} draws)",
        "",
        f"{tail['tests']} tests of a batch's own policy ({tail['skipped']} left out: decided by the threshold or "
        f"not recorded in full); {splits}. A row counts the tests in which none of the first k - 1 null draws "
        "reached the observed distance: 1 / k of them if the batch's frames are exchangeable with the buffer's. "
        "Counts well above that at large k mean more false splits than the rate (docs/guide/clustering.md).",
        "",
        markdown_table(["k", "tests", "expected (tests / k)", "ratio"], rows),
    ]
