"""``covers-dist eval RUN_DIR``: evaluate a saved run's policy bank on every (task, g).

Loads the newest valid checkpoint read-only, and for every base task x every element of the
run's group (seen, unseen and held-out pairs marked) runs ``--episodes`` (default 8) evaluation
episodes per chosen policy and mode, each from its own initial state (a distinct seed per
(group, g, episode), from the ``report`` split of initial states, which the passes during
training, the ones that decide a run's stop, never use; ``--split stop`` replays those): the
policy each episode's own first frames pick task-agnostically by the bank's own assignment rule
(a what-if: the bank does not change; the pair-level choice and how often the two differ are
recorded) and the oracle policy (the one that trained on the pair's group); greedy and stochastic actions. The pass
is appended to ``RUN_DIR/eval.jsonl`` (never to the checkpoints); the per-pair table and the
continual-learning metrics are printed. Serial in this process by default; ``--workers N`` runs
the episodes on N Ray actors of a local, loopback-only Ray instance.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

#: Episodes per (task, g), policy and mode when ``--episodes`` is not given.
DEFAULT_EPISODES = 8


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval",
        help="evaluate a saved run on every (task, g): success and return, agnostic and oracle policies",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory written by covers-dist train")
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES,
                   help=f"episodes per pair, policy and mode, each from its own initial state (default: {DEFAULT_EPISODES})")  # fmt: skip
    p.add_argument("--tasks", help="comma-separated base tasks to evaluate (default: every task of the run)")
    p.add_argument("--modes", help="comma-separated: greedy,stochastic (default: the run's eval.modes)")
    p.add_argument("--selections", help="comma-separated: agnostic,oracle (default: the run's eval.selections)")
    p.add_argument("--split", choices=("report", "stop"), default="report",
                   help="initial states: report (default; never seen by the training passes) or stop (the training passes')")  # fmt: skip
    p.add_argument("--workers", type=int, default=0, help="Ray evaluation actors (default 0: serial, in this process)")
    p.add_argument("--no-write", action="store_true", help="print only; do not append to RUN_DIR/eval.jsonl")
    p.add_argument("--json", action="store_true", help="print the pass and its metrics as JSON")
    p.set_defaults(func=run)


def _csv(value: str | None, name: str) -> list[str] | None:
    if value is None:
        return None
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items:
        raise SystemExit(f"covers-dist eval: --{name} is empty")
    return items


def run(args: argparse.Namespace) -> int:
    from ..config import ConfigError
    from ..evaluation.report import pairs_table
    from ..runtime.checkpoint import CheckpointError
    from ..runtime.evaluation import evaluate_saved_run

    if args.episodes < 1:
        raise SystemExit(f"covers-dist eval: --episodes must be >= 1, got {args.episodes}")
    if args.workers < 0:
        raise SystemExit(f"covers-dist eval: --workers must be >= 0, got {args.workers}")
    try:
        result = evaluate_saved_run(
            args.run_dir,
            episodes=args.episodes,
            tasks=_csv(args.tasks, "tasks"),
            modes=_csv(args.modes, "modes"),
            selections=_csv(args.selections, "selections"),
            workers=args.workers,
            split=args.split,
            write=not args.no_write,
            log=lambda m: print(m, file=sys.stderr),
        )
    except (ValueError, ConfigError, FileNotFoundError, CheckpointError) as e:
        raise SystemExit(f"covers-dist eval: {e}") from None
    ev, cl = result.pass_, result.metrics
    if args.json:
        print(json.dumps({"pass": ev, "metrics": cl}, default=float))
        return 0
    print(f"# {result.run_dir} at iteration {ev['iteration']} ({ev['env_steps']} env steps, {result.checkpoint})")
    print(f"{ev['eval_episodes']} evaluation episodes from {ev['distinct_initial_states']} distinct initial states "
          f"in {ev['time_s']['total']:.1f} s (split {ev.get('split', 'report')})")  # fmt: skip
    if ev.get("episode_choice_disagreement") is not None:
        print(f"agnostic: each episode acted by its own first frames' choice; it differed from the pair-level "
              f"choice in {100 * ev['episode_choice_disagreement']:.1f}% of the episodes")  # fmt: skip
    print()
    print(pairs_table(ev))
    print()
    print(_summary(cl))
    if result.written is not None:
        print(f"\nappended to {result.written}")
    return 0


def _summary(cl: dict[str, Any]) -> str:
    from ..evaluation.report import markdown_table

    rows = [
        [t, g["success"], _interval(g.get("success_counts")), g["success_seen"], g["success_held_out"],
         g["success_oracle"], g["success_stochastic"], g["return"], cl["forgetting"].get(t)]
        for t, g in cl["groups"].items()
    ]  # fmt: skip
    table = markdown_table(
        ["group", "success", "95% interval (n)", "seen", "held-out", "oracle", "stochastic", "return", "forgetting"],
        rows,
    )
    avg = cl.get("average_success")
    zs = cl.get("zero_shot_success")
    fg = cl.get("average_forgetting")
    line = (
        f"average success (groups seen so far) {'n/a' if avg is None else f'{avg:.2f}'}; zero-shot (held-out) "
        f"{'n/a' if zs is None else f'{zs:.2f}'}; average forgetting {'n/a' if fg is None else f'{fg:.2f}'} "
        f"over {cl['passes']} pass(es)"
    )
    return table + "\n\n" + line


def _interval(counts: dict[str, Any] | None) -> str:
    if not counts:
        return "n/a"
    lo, hi = counts["ci95"]
    return f"{lo:.2f}-{hi:.2f} ({counts['successes']}/{counts['n']})"
