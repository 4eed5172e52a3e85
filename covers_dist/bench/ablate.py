"""``covers-dist bench ablate``: the paper's clustering ablations (its Tables 5-8) with training encoders.

Each cell is one real serial training run of the four-group Meta-World stream (``--stream``,
default ``metaworld-multi``; ``metaworld-mono`` for the colour-blind palette) on top of
``--config`` (default ``stream_fast``), with the cell's clustering settings, for every seed of
``--seeds``: the same loop as ``covers-dist bench assign --stream`` (rollout workers, clustering
service, learners in one process), so the encoders the distances read train as the bank assigns.

Cells (``--cells``, comma-separated groups or cell names):

* ``metric``: the paper's fixed-threshold rule (``clustering.rule=threshold``) for each metric
  at three thresholds each (W1 0.6 / 1.0 / 1.4, Euclidean 0.5 / 0.8 / 1.1, Mahalanobis 5 / 10 /
  15; the middle ones are the defaults, distances in units of the buffer's spread);
* ``buffer``: the config's own rule with buffer sizes 32, 64, 128, 256 and 512;
* ``default``: the config as it is.

Per cell and seed: policies created (healed ones included), false splits (created beyond one per
true group), merges, ARI, and wrong-policy episodes (acted by a policy other than their
assignment); then one row per cell, the mean over seeds. ``--json`` prints one object per run.
Every run lasts ``--steps`` env steps (default: 8 of the config's segments, every group about
twice).
"""

from __future__ import annotations

import argparse
import json
import statistics
from typing import Any

from ..commands._common import add_config_args

#: Cell name -> (clustering overrides); the paper's metric x threshold grid and buffer sizes.
METRIC_CELLS: dict[str, list[str]] = {
    f"{metric}@{t}": ["clustering.rule=threshold", f"clustering.metric={metric}", f"clustering.threshold={t}"]
    for metric, ts in (("wasserstein", (0.6, 1.0, 1.4)), ("euclidean", (0.5, 0.8, 1.1)), ("mahalanobis", (5.0, 10.0, 15.0)))
    for t in ts
}
BUFFER_CELLS: dict[str, list[str]] = {f"buffer={n}": [f"clustering.buffer_size={n}"] for n in (32, 64, 128, 256, 512)}
CELLS: dict[str, list[str]] = {"default": [], **METRIC_CELLS, **BUFFER_CELLS}
GROUPS: dict[str, list[str]] = {"default": ["default"], "metric": list(METRIC_CELLS), "buffer": list(BUFFER_CELLS)}
SEGMENTS = 8


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ablate", help="the paper's clustering ablations (metric x threshold, buffer size) with training encoders")
    p.add_argument("--cells", default="default,metric,buffer", help=f"groups {list(GROUPS)} or cell names (default: all)")
    p.add_argument("--seeds", default="0,1", help="comma-separated seeds (default: 0,1)")
    p.add_argument("--stream", default="metaworld-multi", help="metaworld-multi (default) or metaworld-mono")
    p.add_argument("--steps", type=int, default=0, help=f"env steps per run (default: {SEGMENTS} segments of the config)")
    p.add_argument("--json", action="store_true", help="one JSON object per run, then one per cell")
    add_config_args(p, default="stream_fast")
    p.set_defaults(func=run)


def cells_of(spec: str) -> list[str]:
    """The cell names of ``--cells`` (groups expanded, order kept, no repeats)."""
    names: list[str] = []
    for part in (x.strip() for x in spec.split(",")):
        if not part:
            continue
        if part in GROUPS:
            names += GROUPS[part]
        elif part in CELLS:
            names.append(part)
        else:
            raise SystemExit(f"covers-dist bench ablate: unknown cell {part!r}; groups {list(GROUPS)}, cells {list(CELLS)}")
    if not names:
        raise SystemExit("covers-dist bench ablate: --cells names no cell")
    return list(dict.fromkeys(names))


def summarize(cell: str, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean over seeds of one cell's runs."""

    def mean(key: str) -> float | None:
        vals = [float(r[key]) for r in rows if r.get(key) is not None]
        return statistics.fmean(vals) if vals else None

    return {
        "cell": cell,
        "seeds": [r["seed"] for r in rows],
        **{k: mean(k) for k in ("policies_created", "false_splits", "merges", "ari", "wrong_policy_fraction", "wall_s")},
        "ari_min": min((r["ari"] for r in rows if r.get("ari") is not None), default=None),
    }


def run(args: Any) -> int:
    from ..config import load_config
    from ._assign_stream import STREAMS, run_stream

    if args.stream not in ("metaworld-multi", "metaworld-mono"):
        raise SystemExit(f"covers-dist bench ablate: --stream must be metaworld-multi or metaworld-mono, got {args.stream!r}")
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"covers-dist bench ablate: --seeds must be comma-separated integers, got {args.seeds!r}") from None
    if not seeds or any(s < 0 for s in seeds):
        raise SystemExit(f"covers-dist bench ablate: --seeds must name seeds >= 0, got {args.seeds!r}")
    if args.steps < 0:
        raise SystemExit("covers-dist bench ablate: --steps must be >= 1")
    names = cells_of(args.cells)
    base = load_config(args.config, STREAMS[args.stream][1] + list(args.overrides))
    steps = args.steps or SEGMENTS * base.env.episodes_per_task * base.env.max_episode_steps
    c = base.clustering
    total, done, summaries = len(names) * len(seeds), 0, []
    for cell in names:
        rows = []
        for seed in seeds:
            extra = list(args.overrides) + CELLS[cell]
            cfg = load_config(args.config, STREAMS[args.stream][1] + extra)
            row = run_stream(
                args.stream, cfg.clustering.rule, c.assign_at, steps, c.update_every, seed, extra, args.config
            )
            row["cell"] = cell
            rows.append(row)
            done += 1
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                print(
                    f"[{done}/{total}] {cell} seed {seed}: {row['policies_created']} policies created for "
                    f"{row['true_groups']} groups ({row['merges']} merged), ARI {_f(row['ari'])}, wrong-policy "
                    f"episodes {_f(row['wrong_policy_fraction'])}, {row['wall_s']:.0f} s",
                    flush=True,
                )
        summaries.append(summarize(cell, rows))
    if args.json:
        for s in summaries:
            print(json.dumps(s), flush=True)
        return 0
    print(
        f"\n{args.stream}, {steps} env steps per run, seeds {seeds}, on {args.config} "
        f"(feature source {c.feature_source}, healing {'on' if c.merge_threshold else 'off'})\n"
    )
    print("| cell | policies created | false splits | merges | ARI (mean / min) | wrong-policy episodes |")
    print("|---|---|---|---|---|---|")
    for s in summaries:
        print(
            f"| {s['cell']} | {_f(s['policies_created'], 1)} | {_f(s['false_splits'], 1)} | {_f(s['merges'], 1)} | "
            f"{_f(s['ari'])} / {_f(s['ari_min'])} | {_f(s['wrong_policy_fraction'])} |"
        )
    return 0


def _f(v: Any, digits: int = 3) -> str:
    return "n/a" if v is None else f"{float(v):.{digits}f}"
