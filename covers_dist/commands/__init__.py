"""Subcommands of ``covers-dist``: one module per command, each with ``register(subparsers)``."""
