"""Saving a training run's state into a checkpoint and restoring it (the layout is
:mod:`covers_dist.runtime.checkpoint`'s).

A checkpoint holds the driver's counters, stream position and RNG states (``driver.json``), the
config, the policy bank (the clustering service saves it) and every learner's state. An update
still in flight (pipelined loop) is waited for but not published: the learner's state holds it,
and the weights workers sample with until it is published are saved beside it, so a resumed run
goes on exactly as an uninterrupted one.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
import yaml

from ..config import config_to_dict
from ..storage import pack_dir, unpack_dir
from .checkpoint import load_state, write_checkpoint
from .ray_setup import resolve_weights
from .run_storage import drop_live_state, push_checkpoint
from .saved_run import probe_mismatch
from .tally import loss_fields
from .weights import CompletedUpdate

__all__ = ["save_trainer", "restore_trainer"]


def _driver_state(trainer: Any) -> dict[str, Any]:
    return {
        "iteration": trainer.iteration,
        "next_episode": trainer.next_episode,
        "env_steps": trainer.env_steps,
        "current_policy": trainer.current_policy,
        "weight_version": trainer.weights.version,
        "policy_versions": {str(pid): v for pid, v in trainer.weights.versions.items()},
        "policies": sorted(trainer.weights.versions),
        "groups": trainer.tally.groups,
        "acted_other": trainer.tally.acted_other,
        "policy_success": {str(pid): v for pid, v in trainer.tally.policy_success.items()},
        # each group's latest training success and return: the rows after a resume carry them as the
        # unbroken run's do
        "success": trainer.tally.success,
        "returns": trainer.tally.returns,
        "stream": trainer.stream.state_dict(),  # its position: every draw is a function of the seed and the episode
        "network_probe": trainer.backend.network_probe().tolist(),
    }


def save_trainer(trainer: Any) -> Path:
    """Write a checkpoint of ``trainer`` (a :class:`~covers_dist.runtime.driver.Trainer`); its path."""
    weights, backend = trainer.weights, trainer.backend
    pending = weights.complete_pending()

    def write(tmp: Path) -> None:
        state = _driver_state(trainer)
        if pending is not None:
            policy_id, stats, _ = pending
            state["pending_update"] = {"policy_id": policy_id, "stats": loss_fields(stats)}
        (tmp / "driver.json").write_text(json.dumps(state))
        (tmp / "config.yaml").write_text(yaml.safe_dump(config_to_dict(trainer.cfg), sort_keys=False))
        # the bank comes to the driver as bytes: the clustering actor may run on a node without this disk
        unpack_dir(backend.call_clustering("snapshot"), tmp / "bank")
        (tmp / "learners").mkdir()
        for pid in sorted(weights.versions):
            torch.save(backend.call_learner(pid, "state_dict"), tmp / "learners" / f"policy-{pid}.pt")
        if pending is not None:
            sampling = resolve_weights(weights.handles[pending[0]])
            torch.save(sampling, tmp / "learners" / f"sampling-{pending[0]}.pt")

    path = write_checkpoint(trainer.run_dir, trainer.iteration, write)
    push_checkpoint(trainer.cfg, path)  # a copy on the run's storage, when that is apart from the run directory
    return path


def restore_trainer(trainer: Any, path: Path) -> None:
    """Load the checkpoint at ``path`` into a freshly built ``trainer``."""
    weights, backend = trainer.weights, trainer.backend
    state = json.loads((path / "driver.json").read_text())
    trainer.iteration = state["iteration"]
    trainer.next_episode = state["next_episode"]
    trainer.env_steps = state["env_steps"]
    trainer.current_policy = state["current_policy"]
    weights.version = state["weight_version"]
    trainer.tally.groups.update(state.get("groups", {}))
    trainer.tally.acted_other = int(state.get("acted_other", 0))
    trainer.tally.policy_success = {int(pid): list(v) for pid, v in state.get("policy_success", {}).items()}
    trainer.tally.success = {t: float(v) for t, v in state.get("success", {}).items()}
    trainer.tally.returns = {t: float(v) for t, v in state.get("returns", {}).items()}
    trainer.stream.load_state_dict(state["stream"])
    warning = probe_mismatch(state.get("network_probe"), backend.network_probe(), trainer.cfg)
    if warning:
        trainer.log(f"warning: {path}: {warning}")
    backend.call_clustering("restore", pack_dir(path / "bank"))
    pending = state.get("pending_update")
    drop_live_state(trainer.cfg, keep_policies=state["policies"])  # policies created after this checkpoint
    versions = state.get("policy_versions", {})
    for pid in state["policies"]:
        backend.ensure_learner(pid)
        learner_state = load_state(path / "learners" / f"policy-{pid}.pt", str(path / "learners" / f"policy-{pid}.pt"))
        backend.call_learner(pid, "load_state_dict", learner_state)
        weights.learner_versions[pid], newest = backend.call_learner(pid, "weights")
        # published under the version it had (a checkpoint before policy_versions: a new one), so the
        # run-wide counter goes on as in the unbroken run
        version = versions.get(str(pid))
        if pending is not None and pending["policy_id"] == pid:
            # the update in flight when the checkpoint was written: workers keep sampling with
            # the weights before it until the next iteration publishes it, as they would have
            sampling = load_state(path / "learners" / f"sampling-{pid}.pt", str(path / "learners" / f"sampling-{pid}.pt"))
            weights.publish(pid, sampling, version)
            stats = {k.split("/", 1)[1]: v for k, v in pending["stats"].items()}
            weights.pending = (pid, CompletedUpdate(stats, backend.publish(newest)))
        else:
            weights.publish(pid, newest, version)
    weights.prepare_next_learner()
    trainer.evaluation.rewind(trainer.iteration)
    trainer.log(f"resumed from {path} (iteration {trainer.iteration}, {trainer.env_steps} env steps)")
