"""The driver's book of policy weights: which version of each policy is published, and the
update in flight.

Every publication gets a new run-wide version number; rollout workers and the clustering service
pull a policy's weights only when its version changed. A learner's own version counts the
updates applied to it, so a retried update from the same base version is applied once. In the
pipelined loop one update at a time is left running between iterations (``pending``): it is
waited for and published at the next iteration, and a checkpoint saves it unpublished.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["PolicyWeights", "CompletedUpdate", "SubmittedUpdate"]


@dataclass(frozen=True)
class SubmittedUpdate:
    """An update running on its learner: the backend's handle of it, and the iteration whose batch
    it trains on (its statistics will name it, with the policy, as ``batch_iteration`` and
    ``batch_policy``)."""

    future: Any
    iteration: int


@dataclass(frozen=True)
class CompletedUpdate:
    """An update that has finished on its learner but whose weights are not published yet."""

    stats: dict[str, Any]
    handle: Any


class PolicyWeights:
    """Published weights per policy, the learners' versions and the update in flight."""

    def __init__(self, backend: Any, single_policy: bool, learner_ahead: bool = True) -> None:
        self.backend = backend
        self.single_policy = single_policy  # baselines that keep one network: no next learner to prepare
        self.learner_ahead = learner_ahead  # runtime.learner_ahead
        self.version = 0  # the newest run-wide version handed out
        self.versions: dict[int, int] = {}  # policy -> version of its published weights
        self.handles: dict[int, Any] = {}  # policy -> object-store handle of those weights
        self.learner_versions: dict[int, int] = {}  # each learner's version once its submitted updates are done
        self.pending: tuple[int, SubmittedUpdate | CompletedUpdate] | None = None  # (policy id, update)

    # ---- publishing --------------------------------------------------------------------------
    def published(self) -> dict[int, tuple[int, Any]]:
        """``{policy id: (version, handle)}`` of the published weights (what workers sample with)."""
        return {pid: (self.versions[pid], self.handles[pid]) for pid in self.versions}

    def publish(self, policy_id: int, weights: Any, version: int | None = None) -> None:
        """New weights (a state dict) to the object store under a new version (``version``: the
        one they had when a checkpoint was written, on a resume)."""
        self.publish_handle(policy_id, self.backend.publish(weights), version)

    def publish_handle(self, policy_id: int, handle: Any, version: int | None = None) -> None:
        """Weights already in the object store get a new version (or ``version``, restored); the
        clustering service (features, the HTTP service's act) loads them now, workers when they
        next sample with them."""
        if version is None:
            self.version += 1
        self.versions[policy_id] = self.version if version is None else int(version)
        self.handles[policy_id] = handle
        self.backend.call_clustering("sync_weights", {policy_id: (self.versions[policy_id], handle)})

    def start_policy(self, policy_id: int) -> None:
        """A new policy's learner, its initial weights published; the next learner started ahead."""
        self.backend.ensure_learner(policy_id)
        self.learner_versions[policy_id], weights = self.backend.call_learner(policy_id, "weights")
        self.publish(policy_id, weights)
        self.prepare_next_learner()

    def prepare_next_learner(self) -> None:
        """Start the next policy's learner ahead of time (the bank numbers policies 0, 1, 2, ...),
        unless the method keeps a single policy or ``runtime.learner_ahead`` is off."""
        if self.learner_ahead and not self.single_policy:
            self.backend.prepare_learner(max(self.versions) + 1)

    # ---- updates -----------------------------------------------------------------------------
    def submit_update(self, policy_id: int, episodes: Any, iteration: int) -> None:
        """Submit PPO on ``episodes`` to the policy's learner (the serial backend runs it here).
        ``iteration``: the number of the metrics row (and of ``episodes.jsonl``'s ``iteration``) of
        the iteration that sampled them; the update's statistics name it and the policy
        (``batch_iteration``, ``batch_policy``), so a pipelined row, which reports the previous
        iteration's update, says whose it is."""
        base = self.learner_versions[policy_id]  # a retried update from this version is applied once
        self.pending = (policy_id, SubmittedUpdate(self.backend.submit_update(policy_id, episodes, base), iteration))
        self.learner_versions[policy_id] = base + 1

    def complete_pending(self) -> tuple[int, dict[str, Any], Any] | None:
        """Wait for the submitted update (if any) without publishing it: (policy, statistics, weights handle)."""
        if self.pending is None:
            return None
        policy_id, update = self.pending
        if isinstance(update, SubmittedUpdate):
            stats, handle = self.backend.collect_update(update.future)
            batch = {"batch_policy": policy_id, "batch_iteration": update.iteration}
            update = CompletedUpdate({**stats, **batch}, handle)
            self.pending = (policy_id, update)
        return policy_id, update.stats, update.handle

    def finish_update(self) -> dict[str, Any]:
        """Wait for the submitted update (if any) and publish its weights; its statistics ({} if none)."""
        done = self.complete_pending()
        if done is None:
            return {}
        self.pending = None
        policy_id, stats, handle = done
        self.publish_handle(policy_id, handle)
        return stats

    def newest(self) -> dict[int, tuple[int, Any]]:
        """``{policy id: (version, handle)}`` of every policy's newest weights, the update still in
        flight included: it is waited for but not published, so training's schedule is unchanged
        (its version is negative: never one that workers hold). What evaluation acts with."""
        weights_map = self.published()
        done = self.complete_pending()
        if done is not None:
            weights_map[done[0]] = (-(self.version + 1), done[2])
        return weights_map
