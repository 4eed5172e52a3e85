"""The learner: PPO updates of one policy, keeping its optimizer state across visits.

A plain class; :mod:`covers_dist.runtime.actors` makes it a Ray actor (one per policy, created
when the clustering creates the policy). Weights leave the learner as CPU state dicts in the
model's documented mode (see :meth:`covers_dist.models` ``get_weights``), tagged with a version
that increases by one per update, so workers pull them only when they changed.

Surviving a crash (``run_dir`` given, as on Ray): after every update the learner writes its whole
state (weights, Adam moments, schedule counters, shuffling RNG, version) and the result of its
last two updates to ``RUN_DIR/learners_live/policy-N.pt``, atomically, before it returns. A
restarted actor (Ray runs the constructor again) loads that file, so it comes back with the
policy's newest weights, optimizer state and version instead of fresh random weights. Updates
carry the version they start from (``base_version``): a retried call whose update was already
applied returns the stored result instead of applying it again, so every update is applied
exactly once, and a re-executed call (Ray's lineage reconstruction of lost weights) returns the
same weights. The live file, not the object store or the last checkpoint, is the source because
it is the only one that is current after every update and outlives both the process and its node
(``runtime.run_dir`` is on storage every node mounts, see deploy/README.md).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from ..config import Config
from ..envs import suite_layout
from ..models import build_actor_critic
from ..ppo import PPOLearner

__all__ = ["PolicyLearner", "policy_seed", "LIVE_DIR", "live_state_path"]

#: Directory of the run that holds each learner's state after its newest update.
LIVE_DIR = "learners_live"
#: Results kept for retried updates: the newest one and the one before (pipelined loop: the
#: weights workers sample with and the update still in flight).
KEEP_RESULTS = 2


def policy_seed(base_seed: int, policy_id: int) -> int:
    """Initial-weight seed of a policy: new policies are random, but reproducibly so."""
    return base_seed * 10_007 + policy_id


def live_state_path(run_dir: str | Path, policy_id: int) -> Path:
    return Path(run_dir) / LIVE_DIR / f"policy-{policy_id}.pt"


class PolicyLearner:
    """Owns one policy's network, its PPO optimizer and its weight version."""

    def __init__(self, cfg: Config, policy_id: int, device: str | None = None, run_dir: str | None = None) -> None:
        self.cfg = cfg
        self.policy_id = policy_id
        self.device = device or ("cuda" if cfg.runtime.num_gpus > 0 and torch.cuda.is_available() else "cpu")
        layout = suite_layout(cfg.env.suite, cfg.env.image_size)
        torch.manual_seed(policy_seed(cfg.seed, policy_id))
        self.model = build_actor_critic(cfg.network, layout).to(self.device)
        self.ppo = PPOLearner(self.model, cfg.ppo, seed=policy_seed(cfg.seed, policy_id))
        self.version = 0
        #: version after an update -> (statistics, weights) of that update, newest KEEP_RESULTS
        self.results: dict[int, tuple[dict[str, Any], dict[str, torch.Tensor]]] = {}
        self.live_path = live_state_path(run_dir, policy_id) if run_dir else None
        self.restored = False
        if self.live_path is not None and self.live_path.is_file():
            self._load_live()

    def probe(self) -> Any:
        """This process's :meth:`~covers_dist.models.ActorCritic.probe_outputs` (the cross-process check)."""
        return self.model.probe_outputs()

    def weights(self) -> tuple[int, dict[str, torch.Tensor]]:
        return self.version, self.model.get_weights()

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
        # policy at an older version is used as stored (docs/learning.md, "A batch acted by another policy")
        other = [ep.get("policy_id") is not None and int(ep["policy_id"]) != self.policy_id for ep in flat]
        threads = torch.get_num_threads()
        torch.set_num_threads(self.cfg.runtime.learner_threads)
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
                f"{base_version} was requested: its state is older than the run's (was {LIVE_DIR}/ removed?)"
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
        if self.live_path is None:
            return
        self.live_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.live_path.with_name(f".{self.live_path.name}.{os.getpid()}.tmp")
        torch.save({**self.state_dict(), "results": self.results}, tmp)
        os.replace(tmp, self.live_path)  # a crash leaves the old or the new file, never half of one

    def _load_live(self) -> None:
        assert self.live_path is not None
        try:
            state = torch.load(self.live_path, weights_only=False, map_location=self.device)
        except Exception as e:  # noqa: BLE001 - any unreadable file is the same problem
            raise RuntimeError(
                f"{self.live_path} is unreadable ({type(e).__name__}: {e}); resume the run from its newest "
                "checkpoint (covers-dist train --resume RUN_DIR)"
            ) from e
        self._apply_state(state)
        self.results = dict(state.get("results", {}))
        self.restored = True

    def _apply_state(self, state: dict[str, Any]) -> None:
        if state.get("policy_id") != self.policy_id:
            raise ValueError(f"learner state is for policy {state.get('policy_id')}, not {self.policy_id}")
        self.ppo.load_state_dict(state["ppo"])
        self.version = int(state["version"])


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
