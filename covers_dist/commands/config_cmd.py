"""``covers-dist config``: print the resolved configuration, or describe every field."""

from __future__ import annotations

import argparse

import yaml

from ..config import config_to_dict, describe
from ._common import add_config_args, config_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="print the resolved config (YAML) or describe every field")
    add_config_args(p)
    p.add_argument("--describe", action="store_true", help="list every field with its type, default and meaning")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.describe:
        for name, tp, default, doc in describe():
            print(f"{name:32s} {tp:40s} default={default!r}\n    {doc}")
        return 0
    cfg = config_from_args(args)
    print(yaml.safe_dump(config_to_dict(cfg), sort_keys=False), end="")
    return 0
