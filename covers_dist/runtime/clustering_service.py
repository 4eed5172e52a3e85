"""The clustering service: hosts the policy bank and answers queries about it.

A plain class: in a Ray run it is the named clustering actor (see :mod:`.actors`), in serial mode
the driver calls it directly, and ``covers-dist serve --run-dir`` loads one read-only.

* It receives only the first-k observations of each episode, never whole trajectories.
* Features come from every policy's own network side by side (``clustering.feature_source:
  joint``, the default), from each policy's own network for its own buffer (``own``), from one
  frozen encoder (``shared``) or from a fixed colour histogram of the frame (``colors``). The
  driver passes ``{policy id: (version, weights)}`` with every assignment; weights are loaded only
  when a version changed.
* Single-policy methods (``equi``, ``cnn``) use a bank capped at one policy, so every batch is
  recalled to policy 0 (and the ARI shows what one policy for every group means).
* Crash safety: after each assignment the bank and the service's own counters are written, as one
  object, to ``clustering_live/state.tar`` in the run's storage (``runtime.storage``, see
  :mod:`.run_storage`); a restarted actor, on any node, reloads them, and an assignment retried
  for episodes the bank already holds returns the stored record (no doubles).
* Checkpoints: the bank travels to the driver as bytes (:meth:`snapshot`) and back
  (:meth:`restore`), so the driver writes it into its checkpoint wherever this actor runs.
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..clustering import PolicyBank, load_bank, save_bank
from ..clustering.features import SharedFeatures, color_histogram
from ..clustering.joint import JointFeatures
from ..config import Config, config_to_dict
from ..envs import suite_layout
from ..models import build_actor_critic
from ..storage import pack_dir, unpack_dir
from .learner import policy_seed
from .ray_setup import resolve_weights
from .run_storage import CLUSTERING_LIVE, open_storage

__all__ = ["ClusteringService"]

SINGLE_POLICY_METHODS = ("equi", "cnn")
#: Metric-row keys of evaluation passes (covers_dist.evaluation.metrics.metric_row).
EVAL_PREFIX = "eval/"
#: The live state's object in the run's storage
LIVE_STATE = f"{CLUSTERING_LIVE}/state.tar"
#: The live state's journal: the assignment history in sealed chunks of HISTORY_CHUNK records, each
#: written once; the live state holds the records after the last sealed chunk.
HISTORY_JOURNAL = f"{CLUSTERING_LIVE}/history"
HISTORY_CHUNK = 256


class ClusteringService:
    def __init__(self, cfg: Config, storage: str | None = None, read_only: bool = False) -> None:
        torch.set_num_threads(cfg.runtime.torch_threads)
        self.cfg = cfg
        self.store = open_storage(storage, cfg.runtime.storage_retry_s) if storage and not read_only else None
        self.read_only = read_only
        self.layout = suite_layout(cfg.env.suite, cfg.env.image_size)
        self.models: dict[int, Any] = {}
        self.versions: dict[int, int] = {}
        self._lock = threading.RLock()
        self.last_iteration = -1
        self.last_record: dict[str, Any] | None = None
        self.recorded_through = -1  # newest episode index whose statistics were recorded
        self.progress: dict[str, Any] = {}
        self.evaluation: dict[str, Any] = {}
        self.group_names: dict[int, str] = {i: t for i, t in enumerate(cfg.env.tasks)}
        self.bank = self._new_bank()
        self._sealed = 0  # chunks of the history journal the live state in the storage relies on
        if self.store is not None and self.store.exists(LIVE_STATE):
            self._restore(self.store.read_bytes(LIVE_STATE), persist=False, journal=True)

    # ---- construction ------------------------------------------------------------------------
    def _feature_fn(self) -> Any:
        if self.cfg.clustering.feature_source == "colors":
            return SharedFeatures(color_histogram)
        if self.cfg.clustering.feature_source == "joint":
            return JointFeatures(self._encoders)
        if self.cfg.clustering.feature_source == "shared":
            torch.manual_seed(policy_seed(self.cfg.seed, 0))
            shared = build_actor_critic(self.cfg.network, self.layout).eval()
            return SharedFeatures(shared.features_np)
        return self._own_features

    def _new_bank(self) -> PolicyBank:
        bank = PolicyBank.from_config(self.cfg, self._feature_fn())
        if self.cfg.runtime.method in SINGLE_POLICY_METHODS:
            bank.max_policies = 1
        return bank

    def _encoders(self) -> dict[int, tuple[int, Any]]:
        """``{policy id: (weights version, encoder)}`` of the bank's policies with weights (joint features)."""
        return {pid: (self.versions.get(pid, -1), m.features_np) for pid, m in self.models.items() if pid in self.bank.entries}

    def _own_features(self, policy_id: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        model = self.models.get(policy_id)
        if model is None:
            raise LookupError(f"no weights received yet for policy {policy_id}")
        return model.features_np(obs)

    def probe(self) -> np.ndarray:
        """This process's :meth:`~covers_dist.models.ActorCritic.probe_outputs` (the cross-process check)."""
        model = next(iter(self.models.values()), None)
        if model is None:
            with torch.random.fork_rng(devices=[]):
                model = build_actor_critic(self.cfg.network, self.layout)
        return model.probe_outputs()

    def sync_weights(self, weights_map: dict[int, tuple[int, Any]]) -> None:
        """Load ``{policy id: (version, weights)}``; only versions not loaded yet are fetched."""
        for pid, (version, handle) in weights_map.items():
            pid = int(pid)
            if self.versions.get(pid) == version:
                continue
            weights = resolve_weights(handle)
            if pid not in self.models:
                self.models[pid] = build_actor_critic(self.cfg.network, self.layout)
            self.models[pid].set_weights(weights)
            self.models[pid].eval()
            self.versions[pid] = version

    # ---- the assignment step -------------------------------------------------------------------
    def assign(
        self,
        iteration: int,
        obs: dict[str, np.ndarray],
        episode_indices: list[int],
        group_ids: list[int],
        weights_map: dict[int, tuple[int, Any]],
    ) -> dict[str, Any]:
        """Assign a batch of episodes (their first-k observations); idempotent per iteration."""
        with self._lock:
            if self.read_only:
                raise PermissionError("this clustering service is read-only")
            history = self.bank.history
            if history and list(history[-1].episode_indices) == [int(e) for e in episode_indices]:
                # a retried call (e.g. after this actor restarted): the bank already holds it
                self.last_iteration, self.last_record = iteration, history[-1].to_dict()
                return self.last_record
            self.sync_weights(weights_map)
            record = self.bank.assign(obs, episode_indices=episode_indices, group_ids=group_ids).to_dict()
            self.last_iteration = iteration
            self.last_record = record
            self._persist()
            return record

    def what_if(
        self, obs: dict[str, np.ndarray], group_ids: list[int] | None = None, policies: list[int] | None = None
    ) -> dict[str, Any]:
        """The assignment the bank would make for ``obs``, without changing anything.

        ``group_ids`` (true groups, one per frame) are needed only by a ground-truth bank (COVERS-GT).
        ``policies`` restricts the comparison to those policy ids: an evaluation pass running beside
        training compares with the policies it has weights for, not with one the bank created since
        (whose weights may not have arrived yet).
        """
        with self._lock:
            if not len(self.bank):
                raise LookupError("the policy bank is empty: nothing to compare with yet")
            groups = None
            if self.bank.mode == "ground_truth" and group_ids is not None:
                ids = [int(g) for g in group_ids]
                # one id per frame, but the bank counts episodes (initial_frames frames each): a batch
                # of one group is passed as that group, whatever the frames per episode
                groups = ids[0] if len(set(ids)) == 1 else ids
            return self.bank.what_if(obs, group_ids=groups, policies=policies).to_dict()

    def record_episodes(self, summaries: list[dict[str, Any]]) -> None:
        """Per-policy success and return of finished episodes; a retried call records nothing twice."""
        with self._lock:
            new = [s for s in summaries if int(s["episode_index"]) > self.recorded_through]
            if not new:
                return
            self.recorded_through = max(int(s["episode_index"]) for s in new)
            for s in new:
                pid = int(s.get("assigned_policy", s["policy_id"]))
                if pid in self.bank.entries:
                    self.bank.record_episode_stats(pid, s["success"], s["return"])
            self._persist()

    def report(self, row: dict[str, Any]) -> None:
        """Training progress from the driver (for the metrics endpoints)."""
        with self._lock:
            self.progress = {k: v for k, v in row.items() if isinstance(v, (int, float, str, bool)) or v is None}
            evaluated = {k: v for k, v in self.progress.items() if k.startswith(EVAL_PREFIX)}
            if evaluated:  # the latest evaluation pass's metrics stay until the next pass
                self.evaluation = {**evaluated, "iteration": row.get("iteration")}

    # ---- queries -------------------------------------------------------------------------------
    def current_policy_id(self) -> int | None:
        return self.bank.current_policy_id

    def summary(self) -> dict[str, Any]:
        with self._lock:
            s = self.bank.summary()
            s["group_names"] = {str(k): v for k, v in self.group_names.items()}
            return s

    def policy(self, policy_id: int) -> dict[str, Any]:
        with self._lock:
            if policy_id not in self.bank.entries:
                raise KeyError(policy_id)
            return self.bank.entries[policy_id].summary()

    def last_assignment(self) -> dict[str, Any] | None:
        return self.last_record

    def assignments(self, since: int = 0, limit: int = 100) -> list[dict[str, Any]]:
        with self._lock:
            return [r.to_dict() for r in self.bank.history[since : since + limit]]

    def num_assignments(self) -> int:
        return len(self.bank.history)

    def metrics(self) -> dict[str, Any]:
        with self._lock:
            m = self.bank.metrics()
            m["num_policies"] = len(self.bank)
            m["current_policy_id"] = self.bank.current_policy_id
            m["progress"] = dict(self.progress)
            m["evaluation"] = dict(self.evaluation)
            return m

    def act(self, obs: dict[str, np.ndarray], policy_id: int | None = None, deterministic: bool = True) -> dict:
        """The action of a policy (default: the current one) for a batch of observations."""
        with self._lock:
            pid = self.bank.current_policy_id if policy_id is None else int(policy_id)
            if pid is None or pid not in self.models:
                raise KeyError(pid)
            actions, logp, values = self.models[pid].act(obs, deterministic=deterministic)
            return {"policy_id": pid, "action": actions.tolist(), "value": values.tolist()}

    def ping(self) -> int:
        return os.getpid()

    def config(self) -> dict[str, Any]:
        """The run's config as a plain dict (for services that attach to a running job)."""
        return config_to_dict(self.cfg)

    # ---- persistence ---------------------------------------------------------------------------
    def _service_state(self) -> dict[str, Any]:
        return {
            "last_iteration": self.last_iteration,
            "last_record": self.last_record,
            "recorded_through": self.recorded_through,
            "progress": self.progress,
            "evaluation": self.evaluation,
        }

    def save(self, directory: str, history_from: int = 0) -> None:
        """Bank + service counters into ``directory`` (the bank's own atomic format + a JSON file).

        Policy weights are not part of it: they live in the learners' checkpoint files.
        """
        with self._lock:
            path = Path(directory)
            save_bank(self.bank, path, history_from)
            tmp = path / ".service.json.tmp"
            tmp.write_text(json.dumps(self._service_state()))
            os.replace(tmp, path / "service.json")

    def load(self, directory: str, weights: dict[int, Any] | None = None, journal: bool = False) -> None:
        """Restore bank + counters saved by :meth:`save` (and optionally policy weights);
        ``journal``: the first assignment records come from the live state's history journal."""
        with self._lock:
            path = Path(directory)
            head = self._read_journal if journal else None
            self._sealed = 0  # a whole bank relies on no chunk; a live state's sets it as it reads its journal
            self.bank = load_bank(path, feature_fn=self._feature_fn(), history_head=head)
            if self.cfg.runtime.method in SINGLE_POLICY_METHODS:
                self.bank.max_policies = 1
            service = path / "service.json"
            if service.is_file():
                state = json.loads(service.read_text())
                self.last_iteration = int(state["last_iteration"])
                self.last_record = state["last_record"]
                self.recorded_through = int(state.get("recorded_through", -1))
                self.progress = state.get("progress", {})
                self.evaluation = state.get("evaluation", {})
            self.versions.clear()
            for pid, w in (weights or {}).items():
                self.sync_weights({int(pid): (-1, w)})

    def snapshot(self, history_from: int = 0) -> bytes:
        """:meth:`save`'s files as one archive (what the driver writes into a checkpoint's ``bank/``:
        the whole history; ``history_from``: the live state's, without the journal's records)."""
        with self._lock, tempfile.TemporaryDirectory(prefix="covers-bank-") as tmp:
            self.save(tmp, history_from)
            return pack_dir(tmp)

    def restore(self, data: bytes, weights: dict[int, Any] | None = None) -> None:
        """Load :meth:`snapshot`'s bytes (a checkpoint's ``bank/``); they become the live state."""
        self._restore(data, weights, persist=True)

    def _restore(
        self, data: bytes, weights: dict[int, Any] | None = None, persist: bool = True, journal: bool = False
    ) -> None:
        with self._lock, tempfile.TemporaryDirectory(prefix="covers-bank-") as tmp:
            unpack_dir(data, tmp)
            self.load(tmp, weights, journal=journal)
        if persist and self.store is not None:  # the whole history: no chunk written before is relied on now
            self.store.write_bytes(LIVE_STATE, self.snapshot())

    def _persist(self) -> None:
        """The live state to the storage, in time that does not grow with the history: every
        HISTORY_CHUNK records are sealed into a journal chunk written once (before the live state
        that relies on it), and the live state holds the records after the last sealed chunk."""
        if self.store is None:
            return
        sealed = len(self.bank.history) // HISTORY_CHUNK
        for i in range(self._sealed, sealed):  # chunks the live state in the storage does not rely on yet
            records = [r.to_dict() for r in self.bank.history[i * HISTORY_CHUNK : (i + 1) * HISTORY_CHUNK]]
            self.store.write_bytes(f"{HISTORY_JOURNAL}/{i:06d}.json", json.dumps(records, allow_nan=False).encode())
        self.store.write_bytes(LIVE_STATE, self.snapshot(history_from=sealed * HISTORY_CHUNK))
        self._sealed = sealed

    def _read_journal(self, records: int) -> list[dict[str, Any]]:
        """The first ``records`` assignment records, from the journal's chunks."""
        assert self.store is not None and records % HISTORY_CHUNK == 0
        out: list[dict[str, Any]] = []
        for i in range(records // HISTORY_CHUNK):
            out.extend(json.loads(self.store.read_bytes(f"{HISTORY_JOURNAL}/{i:06d}.json")))
        self._sealed = records // HISTORY_CHUNK  # the live state read relies on these chunks
        return out
