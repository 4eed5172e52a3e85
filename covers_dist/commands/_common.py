"""Helpers shared by subcommands."""

from __future__ import annotations

import argparse

from ..config import Config, load_config


def add_config_args(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    parser.add_argument(
        "--config", default=default, metavar="FILE", help=f"YAML config file (default: {default or 'built-in defaults'})"
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one config field, e.g. --set ppo.lr=1e-4 (repeatable; values are YAML)",
    )


def config_from_args(args: argparse.Namespace) -> Config:
    return load_config(args.config, args.overrides)
