"""Will the run's actors fit the cluster? Checked before anything starts.

Ray queues an actor whose resources no node can give and waits forever; a run whose second
learner can never be placed (one learner per policy, each asking for a whole GPU, on a cluster with
one GPU) would hang at its second policy. :func:`check_fits` refuses such a config up front, from
the nodes Ray reports (``ray.nodes()``), with the numbers and what to change.

What a run needs at least: its rollout workers (1 CPU each), its evaluation actors
(``eval.num_cpus`` each), and one learner per task group of ``env.tasks`` (each task under its
transforms is one group, so the bank needs at least that many policies), plus the one started
ahead (``runtime.learner_ahead``), ``runtime.learners_per_process`` of them to a process; each
learner process asks for ``runtime.learner_num_cpus`` CPUs and
``runtime.num_gpus`` GPUs, fractions allowed (``0.25``: four learners share a GPU). A clustering
that splits a group needs more; the check is for what the stream needs when clustered right.

With an autoscaler, nodes that do not exist yet are not seen: ``runtime.check_fit: false`` turns
the check off.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

from ..config import ConfigError
from .clustering_service import SINGLE_POLICY_METHODS

__all__ = ["ClusterTooSmall", "learners_needed", "check_fits"]

_EPS = 1e-9


class ClusterTooSmall(ConfigError):
    """The run's actors can never all be placed on the cluster's nodes (a config error for this
    cluster: the message names the fields to change)."""


def learners_needed(cfg: Any) -> int:
    """Learner processes alive at once when every group has its policy: one per group, plus the one
    started ahead of the next policy, ``runtime.learners_per_process`` policies to a process; one for
    the single-policy baselines."""
    if cfg.runtime.method in SINGLE_POLICY_METHODS:
        return 1
    policies = len(cfg.env.tasks) + (1 if cfg.runtime.learner_ahead else 0)
    return math.ceil(policies / cfg.runtime.learners_per_process)


def _slots(free: float, ask: float) -> float:
    return math.inf if ask <= 0 else math.floor(free / ask + _EPS)


def check_fits(cfg: Any, nodes: Sequence[Mapping[str, float]]) -> None:
    """Raise :class:`ClusterTooSmall` unless ``nodes`` (each node's total ``{"CPU": .., "GPU": ..}``)
    can hold every rollout worker, every evaluation actor and :func:`learners_needed` learners at
    once. Workers and evaluation actors are placed first, on the nodes with the most free CPUs (as
    Ray's spreading would); learners then fill what is left, node by node."""
    rt = cfg.runtime
    gpu, cpu = float(rt.num_gpus), float(rt.learner_num_cpus)
    need = learners_needed(cfg)
    free = [{"CPU": float(n.get("CPU", 0.0)), "GPU": float(n.get("GPU", 0.0))} for n in nodes]
    total_gpus = sum(n["GPU"] for n in free)
    sizes = [(1.0, rt.num_workers, "rollout worker"), (float(cfg.eval.num_cpus), cfg.eval.workers, "evaluation actor")]
    for ask, count, what in sizes:
        if ask <= 0:
            continue
        for _ in range(count):
            node = max(free, key=lambda n: n["CPU"], default=None)
            if node is None or node["CPU"] + _EPS < ask:
                raise ClusterTooSmall(
                    f"the cluster's {len(free)} node(s) have {sum(float(n.get('CPU', 0)) for n in nodes):g} CPUs; "
                    f"{count} {what}s of {ask:g} CPU each do not fit (runtime.num_workers / eval.workers / eval.num_cpus)"
                )
            node["CPU"] -= ask
    per_node = [min(_slots(n["GPU"], gpu), _slots(n["CPU"], cpu)) for n in free]
    fit = sum(per_node)
    if fit >= need:
        return
    asks = " and ".join(f"{v:g} {k}" for k, v in (("GPU", gpu), ("CPU", cpu)) if v > 0)
    groups = "one policy" if rt.method in SINGLE_POLICY_METHODS else f"{len(cfg.env.tasks)} task groups" + (
        ", plus one started ahead" if rt.learner_ahead else "") + (
        f", {rt.learners_per_process} policies per learner process" if rt.learners_per_process > 1 else "")  # fmt: skip
    why = [f"this run needs {need} learner process{'es' * (need > 1)} at once ({groups}), each asking for {asks}"]
    if gpu > 0:
        why.append(f"the cluster has {total_gpus:g} GPUs on {sum(1 for n in free if n['GPU'] > 0)} node(s)")
        if total_gpus > 0:
            share = math.floor(100 * total_gpus / need) / 100
            why.append(
                f"set runtime.num_gpus to {share:g} or less (learners share a GPU), raise "
                "runtime.learners_per_process, or add GPU nodes"
            )
        else:
            why.append("set runtime.num_gpus: 0 (CPU learners) or add GPU nodes")
    else:
        why.append("lower runtime.learner_num_cpus or add CPU nodes")
    raise ClusterTooSmall(f"the run's learners can never all be placed ({fit:g} fit): " + "; ".join(why)
                          + " (runtime.check_fit: false skips this check, e.g. under an autoscaler)")  # fmt: skip
