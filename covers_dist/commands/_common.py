"""Helpers shared by subcommands."""

from __future__ import annotations

import argparse
import re

from ..config import Config, load_config


class CommaList(argparse.Action):
    """A list-valued flag. The convention of every command: comma-separated (``--tasks a,b``);
    space-separated values (``--tasks a b``) and a mix are accepted too. Stores a list of strings."""

    def __init__(self, option_strings, dest, nargs="+", **kwargs):  # noqa: ANN001
        super().__init__(option_strings, dest, nargs=nargs, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):  # noqa: ANN001
        items = [v.strip() for value in values for v in str(value).split(",") if v.strip()]
        if not items:
            parser.error(f"{option_string}: expected a comma-separated list")
        setattr(namespace, self.dest, items)


_ROLE = re.compile(r":(?:py:)?(?:func|mod|class|data|meth|attr|obj|exc|ref|doc|const):`~?([^`<]*?)(?:\s*<[^>]*>)?`")
_LITERAL = re.compile(r"``(.+?)``", re.S)


def plain_text(text: str | None) -> str | None:
    """Help text without reStructuredText markup: ``x`` and :role:`x` become `x`."""
    if not text:
        return text
    text = _ROLE.sub(lambda m: f"`{m.group(1).rsplit('.', 1)[-1] if m.group(0).count('~') else m.group(1)}`", text)
    return _LITERAL.sub(r"`\1`", text)


def clean_help(parser: argparse.ArgumentParser) -> None:
    """Strip reStructuredText markup from the help texts of ``parser`` and all its subparsers."""
    parser.description = plain_text(parser.description)
    parser.epilog = plain_text(parser.epilog)
    for action in parser._actions:
        if action.help and action.help is not argparse.SUPPRESS:
            action.help = plain_text(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                choice.help = plain_text(choice.help)
            for sub in dict.fromkeys(action.choices.values()):
                clean_help(sub)


def add_config_args(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    parser.add_argument(
        "--config",
        default=default,
        metavar="FILE|NAME",
        help="YAML config: a file, or the name of a shipped config (see `covers-dist config list`) "
        f"(default: {default or 'built-in defaults'})",
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
