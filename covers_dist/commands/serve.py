"""``covers-dist serve``: the HTTP service against a running cluster or a saved run.

* --run-dir RUN_DIR: the newest valid checkpoint of a saved run, loaded read-only in this process
  (--checkpoint RUN_DIR is a deprecated alias);
* --address RAY_ADDRESS --name RUN_NAME: the clustering actor covers-clustering-RUN_NAME of a
  training job on that Ray cluster.

Binds to api.host:api.port (127.0.0.1:8000 unless configured); the bearer token comes from
api.token, api.token_file or $COVERS_API_TOKEN. Stops on SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import dataclasses
import signal
import sys
import threading

from ._common import add_config_args


class _DeprecatedRunDir(argparse.Action):
    """``--checkpoint RUN_DIR``, the old name of ``--run-dir``: stores the same value and warns."""

    def __call__(self, parser, namespace, values, option_string=None):  # noqa: ANN001
        print(f"covers-dist serve: {option_string} is deprecated, use --run-dir (same meaning)", file=sys.stderr)
        setattr(namespace, self.dest, values)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="HTTP service (policies, assignments, metrics, actions) for a running cluster or a saved run",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument(
        "--run-dir", metavar="RUN_DIR", help="serve the newest valid checkpoint of the saved run RUN_DIR (read-only)"
    )
    where.add_argument("--checkpoint", dest="run_dir", action=_DeprecatedRunDir, help=argparse.SUPPRESS)
    where.add_argument("--address", metavar="RAY_ADDRESS", help="Ray cluster address of a running training job")
    p.add_argument("--name", metavar="RUN_NAME", help="run name (config `name`) of the job at --address")
    p.add_argument("--actor", help="full name of the clustering actor (default: covers-clustering-RUN_NAME)")
    p.add_argument("--namespace", help="Ray namespace of the actor (default: search every namespace)")
    p.add_argument("--host", help="bind address (default: api.host, 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (default: api.port; 0 picks a free one)")
    add_config_args(p)
    p.epilog = (
        "With --run-dir the run's own config is used and --config/--set change only its api section; "
        "with --address, --config should be the job's config (observation sizes, run name)."
    )
    p.set_defaults(func=run)


def _config(args: argparse.Namespace):  # noqa: ANN202
    from ..config import ConfigError, apply_overrides, config_from_dict, config_to_dict, load_config, load_run_config

    overrides = list(args.overrides)
    if args.host is not None:
        overrides.append(f"api.host={args.host}")
    if args.port is not None:
        if not 0 <= args.port <= 65535:
            raise ConfigError(f"--port={args.port} must be in 0..65535")
        overrides.append(f"api.port={args.port}")
    if args.run_dir is None:
        return load_config(args.config, overrides)
    from pathlib import Path

    run_cfg = Path(args.run_dir) / "config.yaml"
    if not run_cfg.is_file():
        raise SystemExit(f"covers-dist serve: {args.run_dir} is not a run directory (no config.yaml)")
    data = config_to_dict(load_run_config(run_cfg))
    if args.config is not None:
        data["api"] = dataclasses.asdict(load_config(args.config).api)  # its token too, if it sets one
    bad = [o for o in overrides if not o.strip().startswith("api.")]
    if bad:
        raise ConfigError(f"with --run-dir only api.* fields can be set, got {bad}")
    return config_from_dict(apply_overrides(data, overrides))


def run(args: argparse.Namespace) -> int:
    from ..api import ApiServerThread, create_app
    from ..api.server import LISTENING
    from ..api.sources import RaySource, SourceUnavailable, load_checkpoint_source

    cfg = _config(args)
    if args.run_dir is not None:
        try:
            source, run_cfg, ckpt = load_checkpoint_source(args.run_dir, cfg.api.request_timeout_s)
        except (FileNotFoundError, ValueError) as e:
            raise SystemExit(f"covers-dist serve: {e}") from None
        cfg = dataclasses.replace(run_cfg, api=cfg.api)
        print(f"covers-dist serve: read-only run {args.run_dir} (checkpoint {ckpt.name})", flush=True)
    else:
        from ..runtime.actors import clustering_actor_name

        name = args.actor or (f"covers-clustering-{args.name}" if args.name else clustering_actor_name(cfg))
        try:
            source = RaySource.connect(name, args.namespace, args.address, cfg.api.request_timeout_s)
        except (SourceUnavailable, ConnectionError) as e:
            raise SystemExit(f"covers-dist serve: {e}") from None
        print(f"covers-dist serve: clustering actor {name!r} at {args.address}", flush=True)
    done = threading.Event()  # handlers first: a signal sent as soon as the address is printed stops cleanly
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    server = ApiServerThread(create_app(cfg, source), cfg.api.host, cfg.api.port, log_level="warning").start()
    print(f"{LISTENING}{server.url} (docs: {server.url}/docs)", flush=True)
    while not done.wait(0.5):
        if not server.alive:
            print("covers-dist serve: the HTTP server stopped", file=sys.stderr)
            return 1
    server.stop()
    source.close()
    return 0
