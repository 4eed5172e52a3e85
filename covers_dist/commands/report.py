"""``covers-dist report RUN_DIR``: a Markdown results page beside the run (``RUN_DIR/report.md``).

Reads the run's evaluation passes (``eval.jsonl``: from ``eval.every_iterations`` during training
or from ``covers-dist eval``), its bank (newest valid checkpoint: policies, ARI) and its config,
and writes the table in the COVERS paper's layout, one row per task group (success on seen and
held-out transforms, return, policies, forgetting) with the paper's success beside ours, then the
per-pass table (each group's mean and worst transform at every pass) and the per-(task, g) grid
of the latest pass, and under the calibrated rule the tail of its tests (whether the run's false
splits can exceed the configured rate). ``--reference TASK=RUN_DIR`` (repeatable) adds forward
transfer against a run that trained on that group alone. docs/RESULTS.md explains the page.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="write RUN_DIR/report.md: per-group results in the paper's layout, beside the paper's figures",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory with evaluation passes (eval.jsonl)")
    p.add_argument(
        "--reference",
        action="append",
        default=[],
        metavar="TASK=RUN_DIR",
        help="a single-group run of TASK for forward transfer (repeatable)",
    )
    p.add_argument("--out", help="where to write the page (default: RUN_DIR/report.md)")
    p.set_defaults(func=run)


def build_report(run_dir: str | Path, references: dict[str, str] | None = None) -> str:
    """The Markdown page for ``run_dir`` (see the module doc)."""
    from ..clustering import calibration_tail
    from ..evaluation import continual_metrics, read_passes
    from ..evaluation.report import calibration_tail_section, pairs_table, passes_table, results_table
    from ..runtime.saved_run import load_saved_run

    saved = load_saved_run(run_dir, log=lambda m: print(m, file=sys.stderr))
    passes = read_passes(run_dir, missing_ok=False)
    if not passes:
        raise ValueError(f"{Path(run_dir) / 'eval.jsonl'} holds no evaluation pass: run `covers-dist eval {run_dir}`")
    refs = {}
    for task, ref_dir in (references or {}).items():
        if task not in saved.cfg.env.tasks:
            raise ValueError(f"--reference {task}=...: {task!r} is not a task of this run ({list(saved.cfg.env.tasks)})")
        refs[task] = read_passes(ref_dir, missing_ok=False)
    cl = continual_metrics(passes, refs)
    bank = saved.service.metrics()
    last = passes[-1]
    cfg = saved.cfg
    lines = [
        f"# Results: {cfg.name} ({Path(run_dir).name})",
        "",
        f"Written {time.strftime('%Y-%m-%d %H:%M')} by `covers-dist report`; how to read it: docs/RESULTS.md.",
        "",
        f"- method `{cfg.runtime.method}`, suite `{cfg.env.suite}`, group {cfg.env.group}, tasks {list(cfg.env.tasks)}, "
        f"seed {cfg.seed}",
        f"- budget: {last.get('env_steps')} env steps, iteration {last.get('iteration')} "
        f"(checkpoint {saved.checkpoint.name}); clustering {cfg.clustering.metric}, threshold "
        f"{cfg.threshold}, buffer {cfg.clustering.buffer_size}",
        f"- evaluation: {cl['passes']} pass(es); the latest ({last.get('source')}) ran "
        f"{last.get('episodes_per_job')} episodes per (task, g), policy and mode, seeds apart from training",
        "",
        "## Per task group (greedy actions; policy chosen by the bank unless marked oracle)",
        "",
        results_table(cl, bank, list(cfg.env.tasks)),
        "",
        f"Average success over the groups seen so far: {_f(cl['average_success'])}; zero-shot success on "
        f"held-out transforms: {_f(cl['zero_shot_success'])}; average forgetting: {_f(cl['average_forgetting'])}.",
    ]
    if cl["forward_transfer"]:
        ft = ", ".join(f"{t} {_f(v)}" for t, v in cl["forward_transfer"].items())
        lines += ["", f"Forward transfer against single-group reference runs: {ft}."]
    lines += [
        "",
        "## Every pass: each group's success, mean over its trainable transforms / worst over all of them",
        "",
        passes_table(passes, list(cfg.env.tasks)),
    ]
    lines += ["", "## Every (task, g) at the latest pass", "", pairs_table(last)]
    lines += calibration_tail_section(calibration_tail(saved.service.bank.history))
    lines.append("")
    return "\n".join(lines)


def _f(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}"


def run(args: argparse.Namespace) -> int:
    from ..runtime.checkpoint import CheckpointError

    refs = {}
    for item in args.reference:
        task, sep, path = item.partition("=")
        if not sep or not task or not path:
            raise SystemExit(f"covers-dist report: --reference must look like TASK=RUN_DIR, got {item!r}")
        refs[task] = path
    try:
        text = build_report(args.run_dir, refs)
    except (FileNotFoundError, CheckpointError, ValueError) as e:
        raise SystemExit(f"covers-dist report: {e}") from None
    out = Path(args.out) if args.out else Path(args.run_dir) / "report.md"
    out.write_text(text)
    print(text)
    print(f"written to {out}", file=sys.stderr)
    return 0
