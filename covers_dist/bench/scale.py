"""``covers-dist bench scale``: the loop on a local multi-node Ray cluster, and a time model.

Starts a loopback-only Ray cluster of ``--nodes`` nodes on this machine (``ray.cluster_utils``:
a head plus worker nodes, ``--cpus-per-node`` CPUs each, every process on 127.0.0.1, its own temp
dir), places one rollout worker per node, and measures in one run, for 1..``--nodes`` nodes:

* the sequential loop (``runtime.pipeline=false``): env steps/s, and mean seconds per iteration of
  each phase (sample, assign, update_submit, update_wait, record), the terms of the time model below;
* the pipelined loop: env steps/s end to end.

Time model (per iteration of ``S`` env steps, ``W`` workers at ``r`` steps/s each, an update of
``U`` seconds): sequential ``T = S / (W r) + assign + U + record``; pipelined
``T = max(S / (W r), U) + assign + record``. ``--project-workers`` and
``--project-update-samples-per-s`` (a learner's PPO throughput, e.g. a GPU's; default: the
update throughput measured here) give the projected steps/s of a larger cluster from the measured
per-worker rate and the measured assign and record times.

Nodes on one machine share its cores: with 2 cores, 2 one-CPU nodes measure Ray's placement,
transfer and scheduling across nodes, not more compute. The projection states its inputs.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from ..config import load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scale", help="the loop on a local multi-node Ray cluster (1..N nodes) and a time model")
    p.add_argument("--config", default="configs/quickstart.yaml", help="config (default: configs/quickstart.yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--nodes", type=int, default=2, help="largest number of nodes (default: 2)")
    p.add_argument("--cpus-per-node", type=int, default=1, help="CPUs each node offers (default: 1)")
    p.add_argument("--iterations", type=int, default=4, help="measured iterations per setting (default: 4)")
    p.add_argument("--warmup", type=int, default=1, help="unmeasured iterations first (default: 1)")
    p.add_argument("--project-workers", type=int, default=16, help="workers of the projected cluster (default: 16)")
    p.add_argument(
        "--project-update-samples-per-s", type=float, default=None,
        help="PPO samples/s of the projected learner (default: the update throughput measured here)",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def _cluster(nodes: int, cpus: int) -> Any:
    """A loopback-only cluster of ``nodes`` nodes (started here, shut down by the caller)."""
    from ..runtime.local_cluster import LocalCluster

    cluster = LocalCluster(cpus)
    try:
        for _ in range(nodes - 1):
            cluster.add_node(cpus)
    except BaseException:
        cluster.shutdown()  # its logs kept: an exception is on its way
        raise
    return cluster


def _measure(cfg_path: str, overrides: list[str], nodes: int, cpus: int, iters: int, warmup: int) -> dict[str, float]:
    from .train import _covers

    cluster = _cluster(nodes, cpus)
    try:
        return _covers(cfg_path, overrides, nodes, iters, warmup, address=cluster.address)
    finally:
        cluster.shutdown()


def project(measured: dict[str, float], steps_per_iter: float, workers: int, update_samples_per_s: float,
            epochs: int) -> dict[str, float]:  # fmt: skip
    """Projected seconds per iteration and env steps/s of ``workers`` workers (time model above)."""
    per_worker = measured["sample_steps_per_s"] / measured["workers"]
    sample_s = steps_per_iter / (workers * per_worker)
    update_s = steps_per_iter * epochs / update_samples_per_s
    fixed = measured.get("phase_assign_s", 0.0) + measured.get("phase_record_s", 0.0)
    seq, pipe = sample_s + update_s + fixed, max(sample_s, update_s) + fixed
    return {
        "workers": workers, "per_worker_steps_per_s": round(per_worker, 1), "sample_s": round(sample_s, 3),
        "update_s": round(update_s, 3), "assign_record_s": round(fixed, 3),
        "sequential_steps_per_s": round(steps_per_iter / seq, 1), "pipelined_steps_per_s": round(steps_per_iter / pipe, 1),
        "bound": "update" if update_s > sample_s else "sampling",
    }  # fmt: skip


def run(args: argparse.Namespace) -> int:
    if args.nodes < 1 or args.cpus_per_node < 1 or args.iterations < 1 or args.warmup < 0:
        raise SystemExit("covers-dist bench scale: --nodes, --cpus-per-node, --iterations must be >= 1, --warmup >= 0")
    cfg = load_config(args.config, args.overrides)
    steps_per_iter = cfg.steps_per_update
    out: dict[str, Any] = {"config": args.config, "cpus_per_node": args.cpus_per_node, "steps_per_iter": steps_per_iter}
    for nodes in range(1, args.nodes + 1):
        for mode, extra in (("sequential", ["runtime.pipeline=false"]), ("pipelined", [])):
            r = _measure(args.config, [*args.overrides, *extra], nodes, args.cpus_per_node, args.iterations, args.warmup)
            r["workers"] = nodes
            out[f"{nodes}n_{mode}"] = {k: round(v, 3) for k, v in r.items()}
            if not args.json:
                phases = ", ".join(f"{k[6:-2]} {v:.2f}s" for k, v in r.items() if k.startswith("phase_"))
                print(f"{nodes} node(s), {mode}: {r['env_steps_per_s']:.0f} env steps/s end to end, "
                      f"sampling {r['sample_steps_per_s']:.0f} steps/s; per iteration: {phases}", flush=True)
    base, top = out["1n_sequential"], out[f"{args.nodes}n_sequential"]
    out["sampling_scaling"] = round(top["sample_steps_per_s"] / base["sample_steps_per_s"], 3)
    out["end_to_end_scaling"] = round(out[f"{args.nodes}n_pipelined"]["env_steps_per_s"] / out["1n_pipelined"]["env_steps_per_s"], 3)
    measured_update = steps_per_iter * cfg.ppo.epochs / max(top["update_s_per_iter"], 1e-9)
    rate = args.project_update_samples_per_s or measured_update
    out["measured_update_samples_per_s"] = round(measured_update, 1)
    out["projection"] = project(top, steps_per_iter, args.project_workers, rate, cfg.ppo.epochs)
    out["projection"]["update_samples_per_s"] = round(rate, 1)
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))
    return 0
