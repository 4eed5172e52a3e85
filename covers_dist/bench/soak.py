"""``covers-dist bench soak``: a long toy stream; the cost of an iteration and the memory must not
grow with the run's length.

The serial trainer (every component in this process: rollout, clustering service, learners, logs,
checkpoints) runs a tiny toy config for ``--iterations`` iterations (each 2 episodes of 10 steps,
one PPO epoch), and after every iteration reads the clustering service the way the HTTP service
does (:class:`~covers_dist.api.snapshot.SnapshotCache`: summary, last assignment, metrics and the
new history records). It records each iteration's wall seconds (the snapshot's included), the
snapshot's seconds, the assign and record phases (where the bank is persisted) and the process's
resident memory.

Printed: those figures over the first and the last ``--window`` iterations with the ratio end /
start, and the least-squares slope of each per 1000 iterations over the whole run after the first
window (warm-up). Flat means ratios near 1 and slopes near 0; a cost linear in the run's length
shows as a ratio that grows with ``--iterations``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

SOAK = [
    "runtime.serial=true",
    "runtime.num_workers=1",
    "runtime.envs_per_worker=2",
    "env.max_episode_steps=10",
    "clustering.update_every=2",
    "ppo.epochs=1",
    "ppo.minibatch_size=20",
    "network.channels=[2,4]",
    "network.hidden=8",
    "runtime.log_every_s=1000000",
    "runtime.learner_ahead=false",
    "eval.every_iterations=0",
    "env.image_size=16",
    # the bank's size is not what is soaked: colour features keep it at the three toy groups, and
    # the cap holds it there, so what grows is the run's length alone
    "clustering.feature_source=colors",
    "clustering.max_policies=3",
]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("soak", help="a long toy stream: seconds per iteration and memory at its start and end, "
                       "and their slopes")  # fmt: skip
    p.add_argument("--iterations", type=int, default=3000, help="iterations of the stream (default: 3000)")
    p.add_argument("--window", type=int, default=300, help="iterations averaged at the start and the end (default: 300)")
    p.add_argument("--checkpoint-every", type=int, default=100, help="iterations between checkpoints (default: 100)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="more config overrides (on configs/smoke.yaml and the soak's own)")  # fmt: skip
    p.add_argument("--out", help="keep the run directory here (default: a temp dir, removed)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def _rss_mib() -> float:
    """This process's resident memory (Linux /proc; ru_maxrss elsewhere, a peak)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def slope_per_1000(values: list[float]) -> float:
    """Least-squares slope of ``values`` against their index, per 1000 iterations."""
    if len(values) < 2:
        return 0.0
    x = np.arange(len(values), dtype=np.float64)
    return float(np.polyfit(x, np.asarray(values, dtype=np.float64), 1)[0] * 1000.0)


def summarize(series: dict[str, list[float]], window: int) -> dict[str, dict[str, float]]:
    """Per series: the mean of its first and last ``window`` values, their ratio, and the slope per
    1000 iterations after the first window."""
    out = {}
    for name, values in series.items():
        w = max(1, min(window, len(values) // 3))
        start, end = float(np.mean(values[:w])), float(np.mean(values[-w:]))
        out[name] = {
            "start": start,
            "end": end,
            "ratio": end / start if start > 0 else float("nan"),
            "slope_per_1000": slope_per_1000(values[w:]),
        }
    return out


def soak(iterations: int, window: int, checkpoint_every: int, seed: int, overrides: list[str], run_dir: Path,
         log: Any = print) -> dict[str, Any]:  # fmt: skip
    from ..api.snapshot import SnapshotCache
    from ..api.sources import LocalSource
    from ..config import load_config
    from ..runtime.driver import Trainer

    steps = 2 * 10
    cfg = load_config("configs/smoke.yaml", [*SOAK, f"runtime.total_env_steps={iterations * steps}",
                                             f"runtime.checkpoint_every={checkpoint_every}", f"seed={seed}",
                                             f"runtime.run_dir={run_dir}", *overrides])  # fmt: skip
    trainer = Trainer(cfg, log=lambda *_: None)
    cache = SnapshotCache(LocalSource(trainer.backend.clustering), refresh_s=3600.0)
    series: dict[str, list[float]] = {"iteration_s": [], "snapshot_ms": [], "rss_mib": []}
    last = [time.perf_counter()]
    t0 = time.monotonic()

    def after_iteration() -> None:
        s0 = time.perf_counter()
        cache.refresh()
        now = time.perf_counter()
        series["iteration_s"].append(now - last[0])
        series["snapshot_ms"].append((now - s0) * 1e3)
        series["rss_mib"].append(_rss_mib())
        last[0] = now
        n = len(series["iteration_s"])
        if n % max(1, iterations // 10) == 0:
            rate = n / (time.monotonic() - t0)
            log(f"soak: {n}/{iterations} iterations, {rate:.1f} it/s, "
                f"{series['iteration_s'][-1] * 1e3:.0f} ms last, RSS {series['rss_mib'][-1]:.0f} MiB, "
                f"ETA {(iterations - n) / max(rate, 1e-9):.0f} s")  # fmt: skip

    trainer.on_iteration.append(after_iteration)
    try:
        trainer.run()
    finally:
        trainer.close()
    from ..runtime.logfiles import read_jsonl_segments

    rows = [r for r in read_jsonl_segments(run_dir, "metrics.jsonl") if "time/assign" in r]
    for phase in ("assign", "record"):
        series[f"{phase}_ms"] = [1e3 * float(r.get(f"time/{phase}", 0.0)) for r in rows]
    from ..results.provenance import code_commit, cpu_model

    return {
        "cpu": cpu_model(),
        **code_commit(),
        "iterations": len(series["iteration_s"]),
        "episodes": trainer.next_episode,
        "env_steps": trainer.env_steps,
        "policies": int(trainer.backend.call_clustering("metrics").get("num_policies", 0)),
        "wall_s": round(time.monotonic() - t0, 1),
        "window": window,
        "series": summarize(series, window),
    }


def run(args: argparse.Namespace) -> int:
    if args.iterations < 10 or args.window < 1:
        raise SystemExit("covers-dist bench soak: --iterations must be >= 10 and --window >= 1")
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="covers-soak-"))
    log = (lambda m: print(m, file=sys.stderr, flush=True)) if args.json else print
    quiet = contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()
    try:
        with quiet:  # the trainer's progress lines: not on stdout when it carries the JSON
            report = soak(args.iterations, args.window, args.checkpoint_every, args.seed, args.overrides,
                          out / "run", log)  # fmt: skip
    finally:
        if not args.out:
            import shutil

            shutil.rmtree(out, ignore_errors=True)
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"soak: {report['iterations']} iterations, {report['episodes']} episodes, {report['policies']} policies, "
          f"{report['wall_s']} s")  # fmt: skip
    print(f"{'series':<14} {'first ' + str(args.window):>12} {'last ' + str(args.window):>12} {'ratio':>7} {'slope/1000 it':>14}")
    for name, s in report["series"].items():
        print(f"{name:<14} {s['start']:>12.4g} {s['end']:>12.4g} {s['ratio']:>7.2f} {s['slope_per_1000']:>14.4g}")
    return 0
