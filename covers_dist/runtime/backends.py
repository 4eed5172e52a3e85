"""Where the components run: in this process (serial) or as Ray actors.

Both backends expose the same calls to the driver, so the COVERS loop is written once. The
serial backend calls the plain objects directly (debugging, fast tests, determinism checks);
the Ray backend calls the actors made in :mod:`covers_dist.runtime.actors`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config
from ..models.checks import check_same_function
from .placement import check_fits
from .rollout import EVAL_WORKER_INDEX, EpisodeSpec, merge_first_frames, split_first_frames, training_seeds
from .run_storage import mark_run, storage_location

__all__ = ["SerialBackend", "RayBackend", "RayEvalExecutors"]


class SerialBackend:
    """Every component in this process."""

    name = "serial"

    def __init__(self, cfg: Config, run_dir: Path) -> None:
        from .clustering_service import ClusteringService
        from .rollout import RolloutWorker

        self.cfg = cfg
        self.workers = [RolloutWorker(cfg, i) for i in range(cfg.runtime.num_workers)]
        self.clustering = ClusteringService(cfg, storage_location(cfg, run_dir))
        self.learners: dict[int, Any] = {}
        self._eval: Any = None

    def publish(self, weights: Any) -> Any:
        return weights

    # In this process every submitted call runs at once; its result waits in a (done) handle.
    def submit_sample(
        self, plan: list[list[EpisodeSpec]], policy_id: int, version: int, handle: Any, noise_beta: float | None = None
    ) -> Any:
        return self.sample(plan, policy_id, version, handle, noise_beta)

    def collect_sample(self, pending: Any) -> tuple[list, list, list]:
        return pending

    def submit_update(self, policy_id: int, episodes: Any, base_version: int) -> Any:
        return self.learners[policy_id].update(episodes, base_version)

    def collect_update(self, pending: Any) -> tuple[dict[str, Any], Any]:
        """(statistics, handle of the new weights to publish) of a submitted update."""
        stats, _, weights = pending
        return stats, weights

    def sample(
        self, plan: list[list[EpisodeSpec]], policy_id: int, version: int, handle: Any, noise_beta: float | None = None
    ):
        firsts, summaries, episodes = [], [], []
        for worker, specs in zip(self.workers, plan):
            if not specs:
                continue
            eps = worker.sample(specs, policy_id, version, handle, noise_beta=noise_beta)
            f, s = split_first_frames(eps, self.cfg.clustering.initial_frames)
            firsts += f
            summaries += s
            episodes += eps
        return firsts, summaries, episodes

    def first_frames(self, plan: list[list[EpisodeSpec]]) -> dict[str, np.ndarray]:
        """The first observation of every planned episode (episode order), before any policy acts."""
        parts = [
            (w.first_observations(specs, training_seeds(self.cfg.seed, specs)), specs)
            for w, specs in zip(self.workers, plan)
            if specs
        ]
        return merge_first_frames(parts)

    def call_clustering(self, method: str, *args: Any) -> Any:
        return getattr(self.clustering, method)(*args)

    def ensure_learner(self, policy_id: int) -> None:
        if policy_id not in self.learners:
            from .learner import PolicyLearner

            self.learners[policy_id] = PolicyLearner(self.cfg, policy_id)

    def prepare_learner(self, policy_id: int) -> None:
        """Nothing to prepare in one process (a learner is built when its policy is created)."""

    def spare_learners(self) -> list[int]:
        """Policy ids whose learner was started ahead (none in one process)."""
        return []

    def network_probe(self) -> np.ndarray:
        """The network's probe outputs in this run's processes (saved with each checkpoint)."""
        return self.workers[0].probe()

    def call_learner(self, policy_id: int, method: str, *args: Any) -> Any:
        return getattr(self.learners[policy_id], method)(*args)

    def eval_executors(self) -> Any:
        """One evaluation worker of its own (its envs and model never touch the training workers')."""
        if self._eval is None:
            from ..evaluation import LocalExecutors
            from .rollout import RolloutWorker

            self._eval = LocalExecutors([RolloutWorker(self.cfg, EVAL_WORKER_INDEX)])
        return self._eval

    def shutdown(self) -> None:
        for w in self.workers:
            w.close()
        if self._eval is not None:
            self._eval.close()


class RayBackend:
    """Rollout workers, the named clustering actor and the learner processes (one per policy, or one
    per ``runtime.learners_per_process`` policies), on Ray."""

    name = "ray"

    def __init__(self, cfg: Config, run_dir: Path) -> None:
        import ray

        from .actors import clustering_actor, learner_actor, rollout_actor

        self.ray = ray
        self.cfg = cfg
        if cfg.runtime.check_fit:  # before any actor is queued: one that never fits would wait forever
            check_fits(cfg, [n["Resources"] for n in ray.nodes() if n.get("Alive")])
        self.storage = storage_location(cfg, run_dir)  # what every actor, on any node, writes its state to
        self.run_token = mark_run(self.storage)  # an actor that cannot read it does not see the storage: it stops
        self._learner_cls = learner_actor(cfg)
        self.workers = [
            rollout_actor(cfg).remote(cfg, i, self.storage, self.run_token) for i in range(cfg.runtime.num_workers)
        ]
        self.clustering = clustering_actor(cfg, self.storage, self.run_token)
        self.learners: dict[int, Any] = {}  # policy id -> the learner process (actor) hosting it
        self._pools: dict[int, Any] = {}  # learner process index -> actor (runtime.learners_per_process)
        self._spare: set[int] = set()  # policies whose learner was started ahead (prepare_learner)
        self._eval: RayEvalExecutors | None = None
        self._probes: dict[str, Any] = {}
        actors = {f"rollout worker {i}": w for i, w in enumerate(self.workers)}
        self._check_probes({**actors, "clustering actor": self.clustering})

    def _check_probes(self, actors: dict[str, Any]) -> None:
        """Every actor must compute the same function of the same weights as those checked before
        (:func:`covers_dist.models.checks.check_same_function`); raises ``RuntimeError`` otherwise."""
        names = list(actors)
        outputs = self.ray.get([actors[n].probe.remote() for n in names])
        self._probes.update(zip(names, outputs))
        check_same_function(self._probes)

    def publish(self, weights: Any) -> Any:
        return [self.ray.put(weights)]  # wrapped in a list: workers resolve it only when needed

    def submit_sample(
        self, plan: list[list[EpisodeSpec]], policy_id: int, version: int, handle: Any, noise_beta: float | None = None
    ) -> Any:
        k = self.cfg.clustering.initial_frames
        return [
            w.sample_split.options(num_returns=3).remote(specs, policy_id, version, handle, k, noise_beta)
            for w, specs in zip(self.workers, plan)
            if specs
        ]

    def submit_update(self, policy_id: int, episodes: Any, base_version: int) -> Any:
        return self.learners[policy_id].update.options(num_returns=3).remote(policy_id, episodes, base_version)

    def collect_update(self, pending: Any) -> tuple[dict[str, Any], Any]:
        """Waits for the statistics only: the new weights stay in the object store, and their
        reference is the handle workers and the clustering actor resolve (the driver never holds them)."""
        stats_ref, _, weights_ref = pending
        return self.ray.get(stats_ref), [weights_ref]

    def sample(
        self, plan: list[list[EpisodeSpec]], policy_id: int, version: int, handle: Any, noise_beta: float | None = None
    ):
        return self.collect_sample(self.submit_sample(plan, policy_id, version, handle, noise_beta))

    def collect_sample(self, calls: Any) -> tuple[list, list, list]:
        firsts, summaries, episode_refs = [], [], []
        small = self.ray.get([c[0] for c in calls] + [c[1] for c in calls])
        for f in small[: len(calls)]:
            firsts += f
        for s in small[len(calls) :]:
            summaries += s
        episode_refs = [c[2] for c in calls]  # frames go worker -> learner, not through the driver
        return firsts, summaries, episode_refs

    def first_frames(self, plan: list[list[EpisodeSpec]]) -> dict[str, np.ndarray]:
        calls = [
            (w.first_observations.remote(specs, training_seeds(self.cfg.seed, specs)), specs)
            for w, specs in zip(self.workers, plan)
            if specs
        ]
        frames = self.ray.get([c for c, _ in calls])
        return merge_first_frames(list(zip(frames, [specs for _, specs in calls])))

    def call_clustering(self, method: str, *args: Any) -> Any:
        return self.ray.get(getattr(self.clustering, method).remote(*args))

    def ensure_learner(self, policy_id: int) -> None:
        if policy_id not in self.learners:
            self._spare.discard(policy_id)
            pool = self._pool(policy_id)
            probe = self.ray.get(pool.probe.remote(policy_id))  # builds the learner if not started ahead
            self._probes[f"learner of policy {policy_id}"] = probe
            check_same_function(self._probes)
            self.learners[policy_id] = pool

    def prepare_learner(self, policy_id: int) -> None:
        """Start the learner of the policy the bank would create next, in the background.

        A learner process's start, imports and escnn network build take seconds (measured ~10 s on
        2 busy cores); started ahead, they overlap training instead of stalling the iteration that
        creates the policy. Its weights are seeded by the policy id alone, so nothing else changes.
        In a shared learner process (``runtime.learners_per_process``) only the network is built.
        """
        if policy_id not in self.learners and policy_id not in self._spare:
            self._pool(policy_id).prepare.remote(policy_id)
            self._spare.add(policy_id)

    def spare_learners(self) -> list[int]:
        """Policy ids whose learner was started ahead and has no policy yet (``runtime.learner_ahead``)."""
        return sorted(self._spare)

    def network_probe(self) -> np.ndarray:
        """The network's probe outputs in this run's processes (saved with each checkpoint)."""
        return next(iter(self._probes.values()))

    def _pool(self, policy_id: int) -> Any:
        """The learner process hosting ``policy_id``, started if it is not running yet; its learners
        persist their state after every update (a restarted process reloads it)."""
        from .learner import pool_of  # the learner module builds networks: imported where it is used

        index = pool_of(policy_id, self.cfg.runtime.learners_per_process)
        if index not in self._pools:
            self._pools[index] = self._learner_cls.remote(self.cfg, index, None, self.storage, self.run_token)
        return self._pools[index]

    def learner_processes(self) -> int:
        """Learner processes started so far."""
        return len(self._pools)

    def call_learner(self, policy_id: int, method: str, *args: Any) -> Any:
        return self.ray.get(self.learners[policy_id].call.remote(policy_id, method, *args))

    def eval_executors(self) -> "RayEvalExecutors":
        if self._eval is None:
            self._eval = RayEvalExecutors(self.cfg, self.storage, self.run_token)
            self._check_probes({f"evaluation worker {i}": a for i, a in enumerate(self._eval.actors)})
        return self._eval

    def shutdown(self) -> None:
        evals = self._eval.actors if self._eval is not None else []
        for actor in [*self.workers, *self._pools.values(), self.clustering, *evals]:
            try:
                self.ray.kill(actor, no_restart=True)
            except Exception:  # noqa: BLE001 - already gone
                pass


class RayEvalExecutors:
    """``eval.workers`` evaluation actors (rollout workers reserving ``eval.num_cpus`` each)."""

    def __init__(self, cfg: Config, storage: str | None = None, run_token: str | None = None) -> None:
        import ray

        from .actors import eval_actor

        self.ray = ray
        cls = eval_actor(cfg)
        self.actors = [cls.remote(cfg, EVAL_WORKER_INDEX + i, storage, run_token) for i in range(cfg.eval.workers)]

    @property
    def size(self) -> int:
        return len(self.actors)

    def map(self, method: str, args: list[tuple]) -> list[Any]:
        return self.ray.get([getattr(a, method).remote(*x) for a, x in zip(self.actors, args)])

    def close(self) -> None:
        for a in self.actors:
            try:
                self.ray.kill(a, no_restart=True)
            except Exception:  # noqa: BLE001 - already gone
                pass
