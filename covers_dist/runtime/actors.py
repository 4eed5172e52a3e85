"""The one place where plain components become Ray actors.

* rollout workers: one CPU each, restarted automatically (``max_restarts``) and their calls
  retried (``max_task_retries``); a retried call returns the same episodes (they are seeded by
  episode index), so nothing is lost or doubled;
* the clustering actor: named ``covers-clustering-<run name>`` in namespace ``covers-dist``, no CPU reserved (it is light),
  restarted from its persisted state, with assignments made idempotent by iteration number;
* learners: one per policy, on a GPU when ``runtime.num_gpus > 0``;
* evaluation workers: rollout workers that run evaluation episodes (``eval.num_cpus`` each).
"""

from __future__ import annotations

from typing import Any

import ray

from ..config import Config
from .backends import split_first_frames
from .clustering_service import ClusteringService
from .learner import PolicyLearner
from .rollout import RolloutWorker

__all__ = ["rollout_actor", "eval_actor", "clustering_actor", "learner_actor", "clustering_actor_name"]

MAX_RESTARTS = 8
#: Ray namespace of the named clustering actor (so services can find it from any job).
ACTOR_NAMESPACE = "covers-dist"


class _RolloutHost(RolloutWorker):
    def sample_split(self, specs, policy_id, version, handle, k):  # noqa: ANN001
        episodes = self.sample(specs, policy_id, version, handle)
        firsts, summaries = split_first_frames(episodes, k)
        return firsts, summaries, episodes

    def pid(self) -> int:
        import os

        return os.getpid()


def rollout_actor(cfg: Config) -> Any:
    return ray.remote(num_cpus=1, max_restarts=MAX_RESTARTS, max_task_retries=-1)(_RolloutHost)


def eval_actor(cfg: Config) -> Any:
    """Evaluation workers: rollout workers reserving ``eval.num_cpus`` (0 by default)."""
    return ray.remote(num_cpus=cfg.eval.num_cpus, max_restarts=MAX_RESTARTS, max_task_retries=-1)(RolloutWorker)


def clustering_actor_name(cfg: Config) -> str:
    return f"covers-clustering-{cfg.name}"


def clustering_actor(cfg: Config, run_dir: str) -> Any:
    """Create (or get) the named clustering actor of this run."""
    cls = ray.remote(num_cpus=0, max_restarts=-1, max_task_retries=-1)(ClusteringService)
    return cls.options(
        name=clustering_actor_name(cfg), namespace=ACTOR_NAMESPACE, get_if_exists=True, lifetime=None
    ).remote(cfg, run_dir)


def learner_actor(cfg: Config) -> Any:
    gpus = cfg.runtime.num_gpus if cfg.runtime.num_gpus > 0 else 0
    return ray.remote(num_cpus=cfg.runtime.learner_num_cpus, num_gpus=gpus, max_restarts=MAX_RESTARTS, max_task_retries=-1)(PolicyLearner)
