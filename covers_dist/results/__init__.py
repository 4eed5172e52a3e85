"""Results as files: a run's result file, the docs' tables made from such files, and the
generated configuration reference (``covers-dist results``). Plain modules: no Ray, no FastAPI."""

from .docs import configuration_reference, regenerate, render, update
from .provenance import code_commit, cpu_model, read_starts, record_start
from .summary import ResultError, read_result, summarize
from .tables import KINDS

__all__ = [
    "KINDS",
    "ResultError",
    "code_commit",
    "configuration_reference",
    "cpu_model",
    "read_result",
    "read_starts",
    "record_start",
    "regenerate",
    "render",
    "summarize",
    "update",
]
