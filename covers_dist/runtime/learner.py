"""The learner: PPO updates of one policy, keeping its optimizer state across visits.

A plain class; :mod:`covers_dist.runtime.actors` makes a :class:`LearnerPool` of them a Ray actor
(by default one policy per process, created when the clustering creates the policy;
``runtime.learners_per_process`` puts several policies' learners in one process). Weights leave
the learner as CPU state dicts in the model's documented mode (see :meth:`covers_dist.models`
``get_weights``), tagged with a version that increases by one per update, so workers pull them
only when they changed.

Surviving a crash (``storage`` given, as on Ray): after every update the learner writes its whole
state (weights, Adam moments, schedule counters, shuffling RNG, version) and the result of its
last two updates to ``learners_live/policy-N.pt`` in the run's storage (``runtime.storage``, see
:mod:`.run_storage`), whole, before it returns. A restarted actor (Ray runs the constructor
again, on this node or another) loads that object, so it comes back with the policy's newest
weights, optimizer state and version instead of fresh random weights. Updates carry the version
they start from (``base_version``): a retried call whose update was already applied returns the
stored result instead of applying it again, so every update is applied exactly once, and a
re-executed call (Ray's lineage reconstruction of lost weights) returns the same weights. The live
object, not the object store or the last checkpoint, is the source because it is the only one
that is current after every update and outlives both the process and its node.
"""

from __future__ import annotations

import io
import math
from typing import Any

import torch

from ..config import Config
from ..envs import suite_layout
from ..models import build_actor_critic
from ..ppo import PPOLearner
from ..storage import StorageError
from .checkpoint import CheckpointError, load_state
from .run_storage import LEARNERS_LIVE, open_storage

__all__ = ["PolicyLearner", "LearnerPool", "policy_seed", "live_state_key", "pool_of"]
#: Results kept for retried updates: the newest one and the one before (pipelined loop: the
#: weights workers sample with and the update still in flight).
KEEP_RESULTS = 2


def policy_seed(base_seed: int, policy_id: int) -> int:
    """Initial-weight seed of a policy: new policies are random, but reproducibly so."""
    return base_seed * 10_007 + policy_id


def live_state_key(policy_id: int) -> str:
    """Where in the run's storage the learner of ``policy_id`` keeps its live state."""
    return f"{LEARNERS_LIVE}/policy-{policy_id}.pt"


def learner_threads(cfg: Config) -> int:
    """torch threads for a learner's update: ``runtime.learner_threads``, or with 0 (auto) the cores
    it reserves (``runtime.learner_num_cpus``, rounded up), else 1: a learner without cores of its
    own updates beside the rollout workers, and more threads only oversubscribe the cores."""
    rt = cfg.runtime
    return rt.learner_threads or max(1, math.ceil(rt.learner_num_cpus))


class PolicyLearner:
    """Owns one policy's network, its PPO optimizer and its weight version."""

    def __init__(self, cfg: Config, policy_id: int, device: str | None = None, storage: str | None = None) -> None:
        self.cfg = cfg
        self.policy_id = policy_id
        self.device = device or ("cuda" if cfg.runtime.num_gpus > 0 and torch.cuda.is_available() else "cpu")
        layout = suite_layout(cfg.env.suite, cfg.env.image_size)
        torch.manual_seed(policy_seed(cfg.seed, policy_id))
        self.model = build_actor_critic(cfg.network, layout).to(self.device)
        self.ppo = PPOLearner(self.model, cfg.learner_ppo, seed=policy_seed(cfg.seed, policy_id))
        self.version = 0
        #: version after an update -> (statistics, weights) of that update, newest KEEP_RESULTS
        self.results: dict[int, tuple[dict[str, Any], dict[str, torch.Tensor]]] = {}
        self.store = open_storage(storage, cfg.runtime.storage_retry_s) if storage else None
        self.live_key = live_state_key(policy_id)
        self.restored = False
        if self.store is not None and self.store.exists(self.live_key):
            self._load_live()

    def probe(self) -> Any:
        """This process's :meth:`~covers_dist.models.ActorCritic.probe_outputs` (the cross-process check)."""
        return self.model.probe_outputs()

    def weights(self) -> tuple[int, dict[str, torch.Tensor]]:
        return self.version, self.model.get_weights()

    def averaged_weights(self) -> tuple[int, dict[str, torch.Tensor]]:
        """The version and the moving average of the weights (``ppo.weight_average``; an error when none is kept)."""
        return self.version, self.ppo.averaged_weights()

    def update(
        self, episodes: list[Any], base_version: int | None = None
    ) -> tuple[dict[str, Any], int, dict[str, torch.Tensor]]:
        """One PPO update on the given episodes (lists of object references are resolved).

        ``base_version``: the version the caller expects the update to start from. If this
        learner is already past it (the call is a retry of an update it applied before it was
        restarted, or a re-execution), the stored result of that update is returned unchanged.
        """
        if base_version is not None and base_version != self.version:
            return self._stored_result(base_version)
        flat = _resolve(episodes)
        # a batch acted by another policy (assigned after it was acted, clustering.assign_at:
        # iteration) gets this policy's log-probs and values before its update; one acted by this
        # policy at an older version is used as stored (docs/research/learning.md, "A batch acted by another policy")
        other = [ep.get("policy_id") is not None and int(ep["policy_id"]) != self.policy_id for ep in flat]
        threads = torch.get_num_threads()
        torch.set_num_threads(learner_threads(self.cfg))
        try:
            stats = self.ppo.update(flat, reevaluate=other)
        finally:
            torch.set_num_threads(threads)
        self.version += 1
        stats["policy_id"] = self.policy_id
        stats["version"] = self.version
        weights = self.model.get_weights()
        self.results[self.version] = (stats, weights)
        for old in sorted(self.results)[:-KEEP_RESULTS]:
            del self.results[old]
        self._save_live()
        return stats, self.version, weights

    def _stored_result(self, base_version: int) -> tuple[dict[str, Any], int, dict[str, torch.Tensor]]:
        done = base_version + 1
        if done in self.results:
            stats, weights = self.results[done]
            return dict(stats), done, weights
        if base_version > self.version:
            raise RuntimeError(
                f"learner of policy {self.policy_id} is at version {self.version} but an update from version "
                f"{base_version} was requested: its state is older than the run's (was {LEARNERS_LIVE}/ removed?)"
            )
        raise RuntimeError(
            f"learner of policy {self.policy_id} (version {self.version}) no longer holds the result of the "
            f"update from version {base_version} (it keeps the newest {KEEP_RESULTS})"
        )

    def state_dict(self) -> dict[str, Any]:
        return {"policy_id": self.policy_id, "version": self.version, "ppo": self.ppo.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a checkpointed state; it becomes the live state (results of later updates are dropped)."""
        self._apply_state(state)
        self.results = {}
        self._save_live()

    # ---- the live state --------------------------------------------------------------------------
    def _save_live(self) -> None:
        if self.store is None:
            return
        buf = io.BytesIO()
        torch.save({**self.state_dict(), "results": self.results}, buf)
        self.store.write_bytes(self.live_key, buf.getvalue())  # whole: the old or the new state, never half

    def _load_live(self) -> None:
        assert self.store is not None
        where = self.store.describe(self.live_key)
        try:
            data = self.store.read_bytes(self.live_key)
        except (StorageError, OSError) as e:
            raise RuntimeError(f"the live state {where} cannot be read ({e}); is runtime.storage reachable?") from e
        try:
            state = load_state(data, f"the live state {where}", map_location=self.device)
        except CheckpointError as e:
            raise RuntimeError(f"{e}; resume the run from its newest checkpoint (covers-dist train --resume RUN_DIR)") from None
        self._apply_state(state)
        self.results = dict(state.get("results", {}))
        self.restored = True

    def _apply_state(self, state: dict[str, Any]) -> None:
        if state.get("policy_id") != self.policy_id:
            raise ValueError(f"learner state is for policy {state.get('policy_id')}, not {self.policy_id}")
        self.ppo.load_state_dict(state["ppo"])
        self.version = int(state["version"])


def pool_of(policy_id: int, per_process: int) -> int:
    """The learner process (pool) that hosts ``policy_id`` when ``per_process`` policies share one."""
    return int(policy_id) // int(per_process)


class LearnerPool:
    """The learners of policies ``index * n .. index * n + n - 1`` (``n``: ``runtime.learners_per_process``)
    in one process.

    Each :class:`PolicyLearner` is built the first time a call names its policy, so the pool holds
    no state of its own: a restarted process (Ray runs the constructor again) rebuilds each learner
    from its live state in the storage when it is next called, exactly as a one-policy process does.
    Calls run one at a time, so an update of one policy waits for another's in the same process.
    """

    def __init__(self, cfg: Config, index: int, device: str | None = None, storage: str | None = None) -> None:
        self.cfg = cfg
        self.index = int(index)
        self.per_process = int(cfg.runtime.learners_per_process)
        self.device = device
        self.storage = storage
        self.learners: dict[int, PolicyLearner] = {}

    def hosts(self, policy_id: int) -> bool:
        return pool_of(policy_id, self.per_process) == self.index

    def learner(self, policy_id: int) -> PolicyLearner:
        """The learner of ``policy_id``, built (or restored from its live state) on first use."""
        policy_id = int(policy_id)
        if not self.hosts(policy_id):
            first = self.index * self.per_process
            raise ValueError(
                f"learner process {self.index} hosts policies {first}..{first + self.per_process - 1}, not {policy_id}"
            )
        if policy_id not in self.learners:
            self.learners[policy_id] = PolicyLearner(self.cfg, policy_id, self.device, self.storage)
        return self.learners[policy_id]

    def prepare(self, policy_id: int) -> None:
        """Build the learner of a policy the bank has not created yet (``runtime.learner_ahead``)."""
        self.learner(policy_id)

    def probe(self, policy_id: int) -> Any:
        return self.learner(policy_id).probe()

    def update(
        self, policy_id: int, episodes: list[Any], base_version: int | None = None
    ) -> tuple[dict[str, Any], int, dict[str, torch.Tensor]]:
        return self.learner(policy_id).update(episodes, base_version)

    def call(self, policy_id: int, method: str, *args: Any) -> Any:
        """``method`` of the policy's learner (``weights``, ``averaged_weights``, ``state_dict``, ``load_state_dict``)."""
        return getattr(self.learner(policy_id), method)(*args)


def _resolve(episodes: list[Any]) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    refs = [e for e in episodes if not isinstance(e, (dict, list))]
    if refs:
        import ray

        resolved = dict(zip(map(id, refs), ray.get(refs)))
    for e in episodes:
        if isinstance(e, dict):
            out.append(e)
        elif isinstance(e, list):
            out.extend(_resolve(e))
        else:
            got = resolved[id(e)]
            out.extend(got if isinstance(got, list) else [got])
    return out
