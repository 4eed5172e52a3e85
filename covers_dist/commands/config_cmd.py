"""``covers-dist config``: print the resolved configuration, describe every field, or list the shipped configs."""

from __future__ import annotations

import argparse

import yaml

from ..config import config_to_dict, describe, shipped_configs
from ._common import add_config_args, config_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "config",
        help="print the resolved config (YAML), describe every field, or list the shipped configs",
        description=(
            "Print the resolved config as YAML (the --config file or shipped name, with --set applied). "
            "`covers-dist config list` lists the configs shipped with the package; any of their names "
            "works as --config NAME from any directory."
        ),
    )
    p.add_argument(
        "action", nargs="?", choices=["show", "list"], default="show",
        help="show: print the resolved config (default); list: the shipped configs by name",
    )  # fmt: skip
    add_config_args(p)
    p.add_argument("--describe", action="store_true", help="list every field with its type, default and meaning")
    p.set_defaults(func=run)


def _summary(path, width: int = 88) -> str:  # noqa: ANN001
    """The first sentence of a shipped config's leading comment, its purpose in one line."""
    words = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        words.extend(line.lstrip("#").split())
    text = " ".join(words)
    end = text.find(". ")
    text = text if end < 0 else text[: end + 1]
    return text if len(text) <= width else text[: width - 3].rstrip() + "..."


def run(args: argparse.Namespace) -> int:
    if args.action == "list":
        shipped = shipped_configs()
        width = max(map(len, shipped), default=0)
        for name, path in shipped.items():
            print(f"{name:{width}s}  {_summary(path)}".rstrip())
        return 0
    if args.describe:
        for name, tp, default, doc in describe():
            print(f"{name:32s} {tp:40s} default={default!r}\n    {doc}")
        return 0
    cfg = config_from_args(args)
    print(yaml.safe_dump(config_to_dict(cfg), sort_keys=False), end="")
    return 0
