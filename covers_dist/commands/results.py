"""``covers-dist results``: results as files, and the docs' tables made from them.

    covers-dist results                    # rewrite the generated tables and docs/guide/configuration.md
    covers-dist results --check            # change nothing; exit 1 naming each stale file
    covers-dist results summarize RUN_DIR --role report --out docs/results/stream/NAME.json
    covers-dist results table stream docs/results/stream/*.json   # print one table

``summarize`` turns a finished run (after ``covers-dist eval RUN_DIR --episodes 16``, whose pass
uses the ``report`` split) into a small JSON file: config, seed, role (``tuning``: the seed chose
settings; ``report``: it only reports), commit, CPU, env steps, training minutes, policies, ARI
and per (task, g) the successes with n. A generated table in README.md or docs/*.md sits between
``<!-- table: KIND FILE... -->`` and ``<!-- /table -->`` (kinds: stream, features, distances,
assign, ablate); ``covers-dist results`` rewrites each from its files. Run it from the repository
root (or pass ``--root``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from ..results.summary import ROLES
    from ..results.tables import KINDS

    p = sub.add_parser(
        "results",
        help="rewrite (or --check) the docs' tables from committed result files; summarize a run into one",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("action", nargs="?", choices=["update", "summarize", "table"], default="update",
                   help="update (default): rewrite the generated parts of the docs; summarize: one run's "
                   "result file; table: print one table")  # fmt: skip
    p.add_argument("paths", nargs="*", help="summarize: RUN_DIR; table: KIND FILE...")
    p.add_argument("--check", action="store_true", help="update: change nothing, exit 1 if a generated part is stale")
    p.add_argument("--root", default=".", help="the repository checkout whose docs to update (default: .)")
    p.add_argument("--role", choices=ROLES, help="summarize: tuning (the seed chose settings) or report")
    p.add_argument("--label", help="summarize: the run's name in tables (default: its config's name)")
    p.add_argument("--commit", help="summarize: the code's commit, where the run directory does not record one")
    p.add_argument("--out", type=Path, help="summarize: the result file to write (JSON)")
    p.set_defaults(func=run, _kinds=sorted(KINDS))


def run(args: argparse.Namespace) -> int:
    from ..results import ResultError, render, summarize, update

    try:
        if args.action == "summarize":
            if len(args.paths) != 1 or args.role is None or args.out is None:
                print("covers-dist results summarize: give RUN_DIR, --role tuning|report and --out FILE", file=sys.stderr)
                return 2
            result = summarize(args.paths[0], args.role, args.label, args.commit)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(result, indent=1) + "\n")
            print(f"wrote {args.out}")
            return 0
        if args.action == "table":
            if len(args.paths) < 2:
                print(f"covers-dist results table: give KIND FILE... (kinds: {', '.join(args._kinds)})", file=sys.stderr)
                return 2
            print(render(" ".join(args.paths), Path.cwd()), end="")
            return 0
        if args.paths:
            print(f"covers-dist results: unexpected arguments {args.paths}", file=sys.stderr)
            return 2
        changed = update(args.root, check=args.check)
    except ResultError as e:
        print(f"covers-dist results: {e}", file=sys.stderr)
        return 2
    for name in changed:
        print(f"{'stale' if args.check else 'rewrote'}: {name}")
    if args.check and changed:
        print("run `covers-dist results` to rewrite them", file=sys.stderr)
        return 1
    if not changed:
        print("every generated table is current")
    return 0
