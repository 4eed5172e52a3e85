"""A saved run, loaded read-only: its config, newest valid checkpoint, bank and policy weights.

Used by ``covers-dist eval`` / ``report`` and by ``covers-dist serve --run-dir``. Nothing here
writes into the run directory.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import Config, load_run_config
from .checkpoint import CheckpointError, latest_valid_checkpoint, load_state

__all__ = ["SavedRun", "load_checkpoint", "load_saved_run", "model_weights", "probe_mismatch"]


@dataclass
class SavedRun:
    run_dir: Path
    cfg: Config
    checkpoint: Path
    service: Any  # a read-only ClusteringService holding the bank and every policy's weights
    weights: dict[int, Any]
    versions: dict[int, int]
    driver: dict[str, Any]

    @property
    def weights_map(self) -> dict[int, tuple[int, Any]]:
        """``{policy id: (version, weights)}`` as the evaluation workers take it."""
        return {pid: (self.versions[pid], w) for pid, w in self.weights.items()}


def probe_mismatch(saved: Any, current: Any, cfg: Config) -> str | None:
    """Why a checkpoint's policies may act differently in this process than in training, or None.

    ``saved`` is the ``network_probe`` of a checkpoint's driver.json (the network's
    :meth:`~covers_dist.models.ActorCritic.probe_outputs` in the run's processes), ``current`` this
    process's. Checkpoints written before the probe was saved have none: an equivariant network
    with a space-to-depth stem had, then, a first-layer basis drawn anew in every process.
    """
    from ..models.checks import same_function

    if saved is None:
        if cfg.network.kind == "equivariant" and cfg.network.space_to_depth > 1:
            return (
                "saved before checkpoints recorded the network's probe: its first convolution's basis "
                "(space_to_depth stem) was drawn per process then, so its policies act differently here"
            )
        return None
    if not same_function(current, saved):
        return (
            "this process builds the network differently from the run that wrote it (another escnn or "
            "covers-dist version?): the same weights compute another function here"
        )
    return None


def model_weights(learner_state: Any, param_names: set[str], where: str) -> dict[str, Any]:
    """The model parameters inside a learner checkpoint (``{"ppo": PPOLearner.state_dict(), ...}``)."""
    ppo = learner_state.get("ppo") if isinstance(learner_state, dict) else None
    if not isinstance(ppo, dict):
        raise CheckpointError(f"{where}: no 'ppo' learner state inside")
    for cand in (ppo.get("model"), ppo):
        if isinstance(cand, dict) and param_names <= set(cand):
            return {k: cand[k] for k in param_names}
    raise CheckpointError(f"{where}: the learner state holds no model weights (keys: {sorted(ppo)[:8]})")


def load_saved_run(run_dir: str | Path, log: Any = print) -> SavedRun:
    """The newest valid checkpoint of ``run_dir``, read-only.

    Raises ``FileNotFoundError`` for a missing directory or one that is not a run (no
    config.yaml), :class:`CheckpointError` when no checkpoint verifies.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run directory {str(run_dir)!r} does not exist")
    if not (run_dir / "config.yaml").is_file():
        raise FileNotFoundError(f"{run_dir} is not a run directory (no config.yaml)")
    ckpt = latest_valid_checkpoint(run_dir, log=log)
    if ckpt is None:
        raise CheckpointError(f"{run_dir} has no valid checkpoint under checkpoints/ (has it trained one iteration?)")
    return load_checkpoint(run_dir, ckpt, log=log)


def load_checkpoint(run_dir: str | Path, ckpt: str | Path, log: Any = print) -> SavedRun:
    """The checkpoint directory ``ckpt`` of the run ``run_dir`` (its config, bank and weights), read-only."""
    from ..envs import suite_layout
    from ..models import build_actor_critic
    from .clustering_service import ClusteringService

    run_dir, ckpt = Path(run_dir), Path(ckpt)
    if not (ckpt / "learners").is_dir() or not (ckpt / "bank").is_dir():
        raise CheckpointError(f"{ckpt} is not a checkpoint directory (no learners/ or bank/)")
    cfg = load_run_config(ckpt / "config.yaml" if (ckpt / "config.yaml").is_file() else run_dir / "config.yaml")
    model = build_actor_critic(cfg.network, suite_layout(cfg.env.suite, cfg.env.image_size))
    names = {n for n, _ in model.named_parameters()}
    weights, versions = {}, {}
    for f in sorted((ckpt / "learners").glob("policy-*.pt")):
        pid = int(f.stem.split("-", 1)[1])
        state = load_state(f, str(f))
        weights[pid] = model_weights(state, names, str(f))
        versions[pid] = int(state.get("version", 0)) if isinstance(state, dict) else 0
    service = ClusteringService(cfg, read_only=True)
    service.load(str(ckpt / "bank"), weights=weights)
    driver = json.loads((ckpt / "driver.json").read_text()) if (ckpt / "driver.json").is_file() else {}
    warning = probe_mismatch(driver.get("network_probe"), model.probe_outputs(), cfg)
    if warning:
        log(f"warning: {ckpt}: {warning}")
    return SavedRun(run_dir, cfg, ckpt, service, weights, versions, driver)
