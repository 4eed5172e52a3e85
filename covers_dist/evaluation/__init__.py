"""Evaluation of a policy bank on every (task, g): the protocol, the pass runner, the
continual-learning metrics (plain Python; the runtime and the commands host them)."""

from .metrics import continual_metrics, forgetting, forward_transfer, metric_row, pass_summary
from .protocol import MODES, SELECTIONS, EvalJob, EvalPair, eval_pairs, eval_seed, oracle_policies
from .runner import EVAL_LOG, LocalExecutors, append_pass, read_passes, run_evaluation

__all__ = [
    "EVAL_LOG",
    "MODES",
    "SELECTIONS",
    "EvalJob",
    "EvalPair",
    "LocalExecutors",
    "append_pass",
    "continual_metrics",
    "eval_pairs",
    "eval_seed",
    "forgetting",
    "forward_transfer",
    "metric_row",
    "oracle_policies",
    "pass_summary",
    "read_passes",
    "run_evaluation",
]
