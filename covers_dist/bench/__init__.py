"""Benchmarks behind ``covers-dist bench <name>``: one module each, with ``register(subparsers)``.

Benchmarks print figures and ratios measured in one run (the machine is shared and noisy: they
report medians over repeats), and ``--json`` prints one JSON document per line for tooling.
"""
