"""``covers-dist train``: run COVERS (or a baseline) locally, on a Ray cluster, or serially."""

from __future__ import annotations

import argparse
import json
import sys

from ._common import add_config_args, config_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train on a task stream (starts a loopback-only local Ray unless --address is given)",
        description=(
            "Run Algorithm 1 of COVERS: sample -> assign -> update -> publish. Metrics go to "
            "RUN_DIR/metrics.jsonl, episodes.jsonl and tb/; checkpoints to RUN_DIR/checkpoints/."
        ),
    )
    add_config_args(p, default="smoke")
    p.add_argument(
        "--resume",
        metavar="RUN_DIR",
        help="continue the run in RUN_DIR from its newest valid checkpoint; or give the run's storage URI "
        "(runtime.storage, e.g. s3://bucket/run) to fetch it from there into the run directory it names",
    )
    p.add_argument("--address", help="Ray cluster address (default: start a local instance on 127.0.0.1)")
    p.add_argument("--serial", action="store_true", help="run every component in this process (no Ray)")
    p.add_argument("--run-dir", help="override runtime.run_dir")
    p.add_argument("--overwrite", action="store_true", help="start over in a run directory that holds a run")
    p.add_argument(
        "--resume-existing",
        action="store_true",
        help="continue the run when the run directory already holds one (with that run's own config), "
        "else start it: what a retried or re-applied cluster job runs",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import signal

    from ..runtime.driver import holds_a_run, train
    from ..runtime.run_storage import fetch_run

    for sig in (signal.SIGINT, signal.SIGTERM):  # after the run has stopped, a signal has nothing left to stop
        signal.signal(sig, lambda *_: None)

    if args.resume:
        if args.overrides:
            raise SystemExit("covers-dist train: --set cannot be combined with --resume (the run's config is used)")
        result = train(resume_dir=args.resume, services=_http_service)
    else:
        if args.address:
            args.overrides.append(f"runtime.ray_address={args.address}")
        if args.serial:
            args.overrides.append("runtime.serial=true")
        if args.run_dir:
            args.overrides.append(f"runtime.run_dir={args.run_dir}")
        if args.resume_existing and args.overwrite:
            raise SystemExit("covers-dist train: --resume-existing and --overwrite contradict each other")
        cfg = config_from_args(args)
        if args.resume_existing and holds_a_run(cfg):
            print(f"{cfg.runtime.run_dir} holds a run: continuing it with its own config", flush=True)
            fetch_run(cfg)  # on a fresh node the run is on its storage only
            result = train(resume_dir=cfg.runtime.run_dir, services=_http_service)
        else:
            result = train(cfg, overwrite=args.overwrite, services=_http_service)
    keys = ("status", "checkpoint", "ari", "num_policies", "policy_counts")
    print(json.dumps({k: result.get(k) for k in keys}, default=str), flush=True)
    if result.get("status") == "storage-fault":  # stopped cleanly; the message was logged
        print(f"covers-dist train: stopped by a storage fault: {result.get('error')}", file=sys.stderr, flush=True)
        return 3
    return 0


def _http_service(cfg, clustering):  # noqa: ANN001, ANN202 - the runtime's ``services`` hook
    """The HTTP service next to training when ``api.enabled`` (restarted if it stops)."""
    if not cfg.api.enabled:
        return None
    from ..api import training_service

    return training_service(cfg, clustering)
