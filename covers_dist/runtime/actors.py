"""The one place where plain components become Ray actors.

* rollout workers: one CPU each, restarted automatically (``max_restarts``) and their calls
  retried (``max_task_retries``); a retried call returns the same episodes (they are seeded by
  episode index), so nothing is lost or doubled;
* the clustering actor: named ``covers-clustering-<run name>`` in namespace ``covers-dist``, no CPU reserved (it is light),
  restarted from its persisted state, with assignments made idempotent by iteration number;
* learner processes: one per policy, or one per ``runtime.learners_per_process`` policies (process k
  hosts policies k*n .. k*n+n-1, recorded as ``learner-k``), on a GPU when ``runtime.num_gpus > 0``,
  restarted with each policy's state after its newest update (see :mod:`.learner`); a retried update
  is applied once;
* evaluation workers: rollout workers that run evaluation episodes (``eval.num_cpus`` each).

Every actor records its PID in ``processes/`` of the run's storage when it starts (:mod:`.processes`).
"""

from __future__ import annotations

from typing import Any

import ray

from ..config import Config
from .clustering_service import ClusteringService
from .learner import LearnerPool
from .processes import announce
from .run_storage import check_reachable, storage_location
from .rollout import EVAL_WORKER_INDEX, RolloutWorker, split_first_frames

__all__ = ["rollout_actor", "eval_actor", "clustering_actor", "learner_actor", "clustering_actor_name", "run_namespace"]

#: Restarts of a worker or learner actor before Ray gives up on it (its state survives restarts).
MAX_RESTARTS = 100
#: Prefix of the Ray namespace of a run's named clustering actor (:func:`run_namespace`).
ACTOR_NAMESPACE = "covers-dist"


def _announce(storage: str | None, role: str, index: int | None = None) -> None:
    announce(storage, role, index, node=ray.get_runtime_context().get_node_id())


def _lower_priority(cfg: Config) -> None:
    """Training's bulk work yields the CPU to the latency-bound processes (``runtime.actor_nice``)."""
    import os

    if cfg.runtime.actor_nice > 0 and os.getpriority(os.PRIO_PROCESS, 0) < cfg.runtime.actor_nice:
        os.setpriority(os.PRIO_PROCESS, 0, cfg.runtime.actor_nice)


class _RolloutHost(RolloutWorker):
    def __init__(self, cfg: Config, worker_index: int = 0, storage: str | None = None, run_token: str | None = None) -> None:
        check_reachable(storage or "", run_token, f"rollout worker {worker_index}")
        _lower_priority(cfg)
        super().__init__(cfg, worker_index)
        _announce(storage, "eval" if worker_index >= EVAL_WORKER_INDEX else "worker", worker_index)

    def sample_split(self, specs, policy_id, version, handle, k, noise_beta=None):  # noqa: ANN001
        episodes = self.sample(specs, policy_id, version, handle, noise_beta=noise_beta)
        firsts, summaries = split_first_frames(episodes, k)
        return firsts, summaries, episodes

    def pid(self) -> int:
        import os

        return os.getpid()


class _LearnerHost(LearnerPool):
    def __init__(
        self, cfg: Config, index: int, device: str | None = None, storage: str | None = None, run_token: str | None = None
    ) -> None:
        check_reachable(storage or "", run_token, f"learner process {index}")
        _lower_priority(cfg)
        super().__init__(cfg, index, device, storage)
        _announce(storage, "learner", index)


class _ClusteringHost(ClusteringService):
    def __init__(self, cfg: Config, storage: str, run_token: str | None = None) -> None:
        check_reachable(storage, run_token, "the clustering actor")
        super().__init__(cfg, storage)
        _announce(storage, "clustering")


def rollout_actor(cfg: Config) -> Any:
    return ray.remote(num_cpus=1, max_restarts=MAX_RESTARTS, max_task_retries=-1)(_RolloutHost)


def eval_actor(cfg: Config) -> Any:
    """Evaluation workers: rollout workers reserving ``eval.num_cpus`` (0 by default)."""
    return ray.remote(num_cpus=cfg.eval.num_cpus, max_restarts=MAX_RESTARTS, max_task_retries=-1)(_RolloutHost)


def clustering_actor_name(cfg: Config) -> str:
    return f"covers-clustering-{cfg.name}"


def run_namespace(cfg: Config) -> str:
    """The Ray namespace of this run's clustering actor: one per run storage (``runtime.storage``,
    else the run directory's absolute path), so two runs of one config on one cluster never share a
    bank; a resumed run gets its own back. Services find the actor by name in every namespace
    (``covers-dist serve --address``)."""
    import hashlib

    where = storage_location(cfg)
    return f"{ACTOR_NAMESPACE}-{hashlib.sha256(where.encode()).hexdigest()[:12]}"


def clustering_actor(cfg: Config, storage: str, run_token: str | None = None) -> Any:
    """Create (or get) the named clustering actor of this run."""
    cls = ray.remote(num_cpus=0, max_restarts=-1, max_task_retries=-1)(_ClusteringHost)
    return cls.options(
        name=clustering_actor_name(cfg), namespace=run_namespace(cfg), get_if_exists=True, lifetime=None
    ).remote(cfg, storage, run_token)


def learner_actor(cfg: Config) -> Any:
    gpus = cfg.runtime.num_gpus if cfg.runtime.num_gpus > 0 else 0
    return ray.remote(num_cpus=cfg.runtime.learner_num_cpus, num_gpus=gpus, max_restarts=MAX_RESTARTS, max_task_retries=-1)(_LearnerHost)
