"""The ``covers-dist`` command line.

Subcommands are discovered: every module in :mod:`covers_dist.commands` that defines
``register(subparsers)`` adds one subcommand, and every module in :mod:`covers_dist.bench`
that defines ``register(subparsers)`` adds one ``covers-dist bench <name>`` benchmark. A
registered parser sets ``func`` (called with the parsed args; returns an exit code).

:func:`main` needs no environment variable: before any subcommand is imported it sets
``MUJOCO_GL`` (and ``PYOPENGL_PLATFORM``) to an installed GL backend unless they are set, and
every path that starts a local Ray instance makes it loopback-only itself
(:func:`covers_dist.runtime.ray_setup.loopback_only`).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from . import __version__
from .commands._common import clean_help
from .config import ConfigError
from .clustering.persistence import CheckpointError
from .runtime.lease import LeaseHeld
from .storage import StorageError


def _discover(package: str) -> list:
    pkg = importlib.import_module(package)
    mods = []
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{package}.{info.name}")
        if hasattr(mod, "register"):
            mods.append(mod)
    return mods


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="covers-dist",
        description="COVERS: continual vision-based RL with group symmetries, as a distributed service.",
    )
    parser.add_argument("--version", action="version", version=f"covers-dist {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _discover("covers_dist.commands"):
        mod.register(sub)
    bench = sub.add_parser("bench", help="benchmarks that print measured figures (listed in docs/guide/usage.md)")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH")
    for mod in _discover("covers_dist.bench"):
        mod.register(bench_sub)
    bench.set_defaults(func=lambda args: (bench.print_help(), 2)[1])
    clean_help(parser)  # module docstrings serve as descriptions: no reStructuredText markup in --help
    return parser


def main(argv: list[str] | None = None) -> int:
    from .envs.gl_render import default_gl_environment

    default_gl_environment()  # before any subcommand module can import mujoco
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except ConfigError as e:
        print(f"covers-dist: config error: {e}", file=sys.stderr)
        return 2
    except (FileNotFoundError, FileExistsError, CheckpointError, LeaseHeld) as e:
        print(f"covers-dist: {e}", file=sys.stderr)
        return 2
    except StorageError as e:  # an outage past its retries, a full disk, storage that cannot be opened
        print(f"covers-dist: storage: {e}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("covers-dist: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
