"""``covers-dist bench sweep``: training runs of one task group under variants of a config, side by side.

How the PPO defaults were chosen (docs/research/learning.md): each ``--variant`` is a list of config
overrides (``"ppo.epochs=4,ppo.minibatch_size=200"``; the empty variant ``""`` is the config as
given); each variant trains ``--steps`` env steps on a stream of the one ``--task`` under the
config's group (every episode a transformed copy ``g.T``, ``env.episodes_per_task=1`` so ``g``
changes every episode), for each ``--seeds`` seed, one run after another, with the real loop
(Ray, or ``--serial``). Reported per run, from its ``metrics.jsonl``: the mean training success
(and return) by fifths of the run, the env steps and wall-clock seconds until the success of a window of
``--window`` iterations first reaches 0.9, the policies the bank made, and the run's wall-clock.

Training success only: tune on these, report on evaluation episodes (``covers-dist bench learn``,
``covers-dist eval``).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..config import ConfigError, load_config

TARGET = 0.9


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help="training runs of one task group under config variants (how defaults are chosen)")
    p.add_argument("--config", default="configs/quickstart.yaml", help="base config (default: configs/quickstart.yaml)")
    p.add_argument("--task", help="the task group to train on (default: the config's first task)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override applied to every variant (repeatable)")  # fmt: skip
    p.add_argument("--variant", dest="variants", action="append", default=None, metavar="K=V,K=V",
                   help="one variant: comma-separated overrides; '' is the config as given (repeatable)")  # fmt: skip
    p.add_argument("--steps", type=int, default=40_000, help="env steps per run (default: 40000)")
    p.add_argument("--seeds", default="0", help="comma-separated seeds (default: 0)")
    p.add_argument("--window", type=int, default=3, help="iterations averaged for the 0.9 crossing (default: 3)")
    p.add_argument("--serial", action="store_true", help="run each training in this process (no Ray)")
    p.add_argument("--out", help="keep the runs under this directory (default: a temporary one, removed)")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    p.set_defaults(func=run)


def summarize(rows: list[dict[str, Any]], task: str, window: int = 3) -> dict[str, Any]:
    """Figures of one run from its metrics rows (one per iteration)."""
    key = f"success/{task}"
    pts = [(r["env_steps"], r[key], r.get("wall_time")) for r in rows if key in r]
    if not pts:
        return {"iterations": 0, "fifths": [], "final": None, "return_fifths": [], "steps_to_0.9": None,
                "wall_s_to_0.9": None}  # fmt: skip
    returns = np.array([r.get(f"return/{task}", np.nan) for r in rows if key in r], float)
    steps = np.array([p[0] for p in pts], float)
    success = np.array([p[1] for p in pts], float)
    fifths = [float(np.mean(part)) for part in np.array_split(success, 5) if len(part)]
    reached_steps = reached_wall = None
    t0 = rows[0].get("wall_time")
    for i in range(max(0, window - 1), len(success)):
        if success[i - window + 1 : i + 1].mean() >= TARGET:
            reached_steps = int(steps[i])
            if t0 is not None and pts[i][2] is not None:
                reached_wall = round(float(pts[i][2] - t0), 1)
            break
    return {
        "iterations": len(pts),
        "fifths": [round(f, 3) for f in fifths],
        "final": round(fifths[-1], 3),
        "return_fifths": [round(float(np.mean(part)), 1) for part in np.array_split(returns, 5) if len(part)],
        "steps_to_0.9": reached_steps,
        "wall_s_to_0.9": reached_wall,
        "policies": int(max(r.get("num_policies", 1) for r in rows)),
    }


def _variant(text: str) -> list[str]:
    items = [x.strip() for x in text.split(",") if x.strip()]
    bad = [x for x in items if "=" not in x]
    if bad:
        raise SystemExit(f"covers-dist bench sweep: --variant items must be KEY=VALUE, got {bad}")
    return items


def run(args: argparse.Namespace) -> int:
    from ..runtime.driver import train
    from ..runtime.logfiles import read_jsonl_segments

    if args.steps < 1 or args.window < 1:
        raise SystemExit("covers-dist bench sweep: --steps and --window must be >= 1")
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"covers-dist bench sweep: --seeds must be comma-separated integers, got {args.seeds!r}") from None
    variants = [_variant(v) for v in (args.variants if args.variants is not None else [""])]
    base = load_config(args.config, args.overrides)
    task = args.task or base.env.tasks[0]
    common = [*args.overrides, f"env.tasks=[{task}]", "env.episodes_per_task=1", "env.held_out=0",
              f"runtime.total_env_steps={args.steps}", "api.enabled=false", "eval.every_iterations=0"]  # fmt: skip
    if args.serial:
        common.append("runtime.serial=true")
    for v in variants:  # every variant is checked before the first run starts
        try:
            load_config(args.config, [*common, *v])
        except ConfigError as e:
            raise SystemExit(f"covers-dist bench sweep: variant {','.join(v) or '(as configured)'}: {e}") from None
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="covers-sweep-"))
    results = []
    total = len(variants) * len(seeds)
    t_all = time.monotonic()
    for n, (v, seed) in enumerate(itertools.product(variants, seeds), start=1):
        name = ",".join(v) or "(as configured)"
        run_dir = out / f"run-{n:02d}"
        cfg = load_config(args.config, [*common, *v, f"seed={seed}", f"runtime.run_dir={run_dir}"])
        print(f"[{n}/{total}] {task} seed {seed}: {name}", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        with contextlib.redirect_stdout(sys.stderr):  # the run's progress lines
            status = train(cfg, overwrite=True).get("status")
        wall = time.monotonic() - t0
        summary = summarize(list(read_jsonl_segments(run_dir, "metrics.jsonl")), task, args.window)
        results.append({"variant": name, "seed": seed, "wall_s": round(wall, 1), **summary})
        if status == "interrupted":  # SIGINT / SIGTERM stop the sweep, not only the run in progress
            results[-1]["interrupted"] = True
            print(f"[{n}/{total}] interrupted: the sweep stops here ({n - 1} runs complete)", file=sys.stderr, flush=True)
            break
        eta = (time.monotonic() - t_all) / n * (total - n)
        print(f"[{n}/{total}] final {summary['final']} fifths {summary['fifths']} "
              f"0.9 at {summary['steps_to_0.9']} steps; {wall:.0f} s; ETA {eta / 60:.0f} min",
              file=sys.stderr, flush=True)  # fmt: skip
    report = {"config": args.config, "task": task, "steps": args.steps, "group": base.env.group, "runs": results}
    if args.json:
        print(json.dumps(report))
    else:
        print(table(report))
    if not args.out:
        import shutil

        shutil.rmtree(out, ignore_errors=True)
    return 0


def table(report: dict[str, Any]) -> str:
    """The runs as a markdown table (what docs/research/learning.md records)."""
    lines = [
        f"{report['task']} under {report['group']}, {report['steps']} env steps per run ({report['config']})",
        "",
        "| variant | seed | success by fifths | final | return by fifths | steps to 0.9 | s to 0.9 | policies | wall s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["runs"]:
        fifths = " ".join(f"{f:.2f}" for f in r["fifths"])
        returns = " ".join(f"{f:.0f}" for f in r.get("return_fifths", []))
        lines.append(f"| {r['variant']} | {r['seed']} | {fifths} | {r['final']} | {returns} | {r['steps_to_0.9'] or '-'} | "
                     f"{r['wall_s_to_0.9'] or '-'} | {r.get('policies', '-')} | {r['wall_s']} |")  # fmt: skip
    return "\n".join(lines)
