"""``covers-dist compare RUN_DIR RUN_DIR ...``: methods side by side on one stream.

Each run directory is one method's run (``runtime.method``: covers, covers-gt, covers-cnn, equi,
cnn) with evaluation passes (``eval.every_iterations`` during training, or ``covers-dist eval``).
Writes ``OUT/compare.md`` (one row per run: per-group greedy success over the trainable
transforms, average, zero-shot success on the held-out pairs, forgetting, policies, ARI, env steps;
the paper's COVERS row beside them) and ``OUT/compare_success.png`` (evaluation success over env
steps, one panel per group and one for the average, one line per run). Runs must share the suite,
tasks, symmetry group, episode length and held-out pairs; the first difference is named.
``--across-seeds`` compares runs of several seeds (which hold out different pairs: each row's
held-out column is its own pairs') and adds a table with one row per method, the mean +- standard
deviation over its seeds. Two more tables come from each run's logs: the critic's fit per group
(median explained variance of the value function over the updates of that group's batches, from
``metrics.jsonl``) and what the other groups' training did to each group (its training return and
success just before a gap in the stream and just after it, ``--reentry-window`` episodes on either
side, from ``episodes.jsonl``). docs/RESULTS.md shows the tables for the paper's stream at a CPU
scale.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compare",
        help="methods side by side: one table and one figure from several runs of one stream",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run directories with evaluation passes")
    p.add_argument("--out", default="runs/compare", help="where compare.md and compare_success.png go")
    p.add_argument("--json", action="store_true", help="print the table's content as JSON instead of Markdown")
    p.add_argument(
        "--across-seeds",
        action="store_true",
        help="runs of several seeds (their held-out pairs may differ): add mean +- std per method",
    )
    p.add_argument(
        "--reentry-window",
        type=int,
        default=8,
        metavar="N",
        help="training episodes on either side of a gap in the re-entry table (default: 8, one iteration)",
    )
    p.set_defaults(func=run)


def _stream_stats(run: Path, window: int, lag: int) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """The run's re-entry changes and value fit per group, from its logs (None where it has none)."""
    from ..evaluation.reentry import reentry_changes, value_fit
    from ..runtime.logfiles import has_log, read_jsonl_segments

    if not has_log(run, "episodes.jsonl"):
        return None, None
    episodes = list(read_jsonl_segments(run, "episodes.jsonl"))
    gaps = reentry_changes(episodes, window=window) or None
    fit = None
    if has_log(run, "metrics.jsonl"):
        fit = value_fit(read_jsonl_segments(run, "metrics.jsonl"), episodes, lag) or None
    return gaps, fit


def load_runs(run_dirs: Sequence[str | Path], window: int = 8) -> list[Any]:
    """:class:`~covers_dist.evaluation.compare.RunResults` of each run directory, labelled
    (``window``: episodes on either side of a gap for the re-entry table)."""
    from ..evaluation import read_passes
    from ..evaluation.compare import RunResults, run_labels
    from ..runtime.saved_run import load_saved_run

    runs: list[RunResults] = []
    seen_dirs: set[Path] = set()
    for d in run_dirs:
        path = Path(d)
        if path.resolve() in seen_dirs:
            raise ValueError(f"{path} is given twice")
        seen_dirs.add(path.resolve())
        saved = load_saved_run(path, log=lambda m: print(m, file=sys.stderr))
        cfg = saved.cfg
        r = RunResults(
            path=str(path),
            method=cfg.runtime.method,
            seed=int(cfg.seed),
            suite=cfg.env.suite,
            tasks=list(cfg.env.tasks),
            group=cfg.env.group,
            max_episode_steps=int(cfg.env.max_episode_steps),
            passes=read_passes(path, missing_ok=False),
            bank=saved.service.metrics(),
        )
        r.reentry, r.value_fit = _stream_stats(path, window, lag=1 if cfg.runtime.pipeline else 0)
        runs.append(r)
    for r, label in zip(runs, run_labels(runs)):
        r.label = label
    return runs


def plot_comparison(runs: Sequence[Any], out: Path) -> Path:
    """``out/compare_success.png``: success over env steps, a panel per group and the average."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from ..evaluation.compare import success_curve
    from ..evaluation.report import group_name

    tasks = list(runs[0].tasks)
    panels = [*tasks, None]
    cols = min(len(panels), 3)
    nrows = -(-len(panels) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.2 * cols, 3.2 * nrows), squeeze=False)
    for ax, task in zip(axes.flat, panels):
        for r in runs:
            steps, values = success_curve(r, task)
            ax.plot(steps, [np.nan if v is None else v for v in values], "o-", ms=3, label=r.label)
        name = "average over groups seen" if task is None else group_name(task)
        ax.set(title=name, xlabel="env steps", ylabel="greedy success", ylim=(-0.05, 1.05))
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    fig.suptitle("evaluation success per method (policy chosen by the bank; trainable transforms)")
    from .plot import _save  # env-step axes read 240k, 1.2M

    return _save(fig, out / "compare_success.png")


def run(args: argparse.Namespace) -> int:
    from ..evaluation.compare import compare_table, comparison_json, methods_table, reentry_table, value_fit_table
    from ..runtime.checkpoint import CheckpointError

    try:
        if args.reentry_window < 1:
            raise ValueError(f"--reentry-window must be >= 1, got {args.reentry_window}")
        runs = load_runs(args.run_dirs, window=args.reentry_window)
        data = comparison_json(runs, across_seeds=args.across_seeds)
        table = compare_table(data, paper=not args.across_seeds)
        if args.across_seeds:
            table = "\n".join(
                ["## Per method, mean +- standard deviation over seeds", "", methods_table(data), "", "## Per run", "", table]
            )
    except (FileNotFoundError, CheckpointError, ValueError) as e:
        raise SystemExit(f"covers-dist compare: {e}") from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if data["held_out"] is not None:
        held = f"held-out pairs {[tuple(p) for p in data['held_out']]}"
    else:
        held = "held-out pairs per run: " + "; ".join(
            f"{r['label']} seed {r['seed']} {[tuple(p) for p in r['held_out']]}" for r in data["runs"]
        )
    budget = ", ".join(f"{r['label']} {r['env_steps']} env steps (iteration {r['iteration']})" for r in data["runs"])
    text = "\n".join(
        [
            "# Methods side by side",
            "",
            f"- stream: suite `{data['suite']}`, group {data['group']}, tasks {data['tasks']}; " + held,
            f"- latest evaluation pass of each run: {budget}",
            "- success: greedy, mean over each group's trainable (task, g) pairs, policy chosen by the bank; "
            "how to read it: docs/RESULTS.md",
            "",
            table,
            "",
        ]
    )
    w = args.reentry_window
    for title, what, table in (
        (
            "The critic's fit per group",
            "Median explained variance of the value function over the PPO updates of each group's batches "
            "(n updates); one network per group fits one group's returns, a shared one all of them.",
            value_fit_table(data),
        ),
        (
            "Across the gaps: each group's training episodes before and after the other groups trained",
            f"Mean training return over the last {w} episodes of a group's segment -> the first {w} of its next one "
            "(change +- standard error over the n re-entries), and the success the same way; stochastic training "
            "episodes, policy chosen by the bank. One network per group changes only by noise here; a shared one by "
            "what the others' updates did to it.",
            reentry_table(data),
        ),
    ):
        if table is not None:
            text += "\n".join(["", f"## {title}", "", what, "", table, ""])
    (out / "compare.md").write_text(text)
    fig = plot_comparison(runs, out)
    print(json.dumps(data, indent=2) if args.json else text)
    print(f"written to {out / 'compare.md'} and {fig}", file=sys.stderr)
    return 0
