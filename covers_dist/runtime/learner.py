"""The learner: PPO updates of one policy, keeping its optimizer state across visits.

A plain class; :mod:`covers_dist.runtime.actors` makes it a Ray actor (one per policy, created
when the clustering creates the policy). Weights leave the learner as CPU state dicts in the
model's documented mode (see :meth:`covers_dist.models` ``get_weights``), tagged with a version
that increases by one per update, so workers pull them only when they changed.
"""

from __future__ import annotations

from typing import Any

import torch

from ..config import Config
from ..envs import suite_layout
from ..models import build_actor_critic
from ..ppo import PPOLearner

__all__ = ["PolicyLearner", "policy_seed"]


def policy_seed(base_seed: int, policy_id: int) -> int:
    """Initial-weight seed of a policy: new policies are random, but reproducibly so."""
    return base_seed * 10_007 + policy_id


class PolicyLearner:
    """Owns one policy's network, its PPO optimizer and its weight version."""

    def __init__(self, cfg: Config, policy_id: int, device: str | None = None) -> None:
        self.cfg = cfg
        self.policy_id = policy_id
        self.device = device or ("cuda" if cfg.runtime.num_gpus > 0 and torch.cuda.is_available() else "cpu")
        layout = suite_layout(cfg.env.suite, cfg.env.image_size)
        torch.manual_seed(policy_seed(cfg.seed, policy_id))
        self.model = build_actor_critic(cfg.network, layout).to(self.device)
        self.ppo = PPOLearner(self.model, cfg.ppo, seed=policy_seed(cfg.seed, policy_id))
        self.version = 0

    def weights(self) -> tuple[int, dict[str, torch.Tensor]]:
        return self.version, self.model.get_weights()

    def update(self, episodes: list[Any]) -> tuple[dict[str, Any], int, dict[str, torch.Tensor]]:
        """One PPO update on the given episodes (lists of object references are resolved)."""
        flat = _resolve(episodes)
        threads = torch.get_num_threads()
        torch.set_num_threads(self.cfg.runtime.learner_threads)
        try:
            stats = self.ppo.update(flat)
        finally:
            torch.set_num_threads(threads)
        self.version += 1
        stats["policy_id"] = self.policy_id
        stats["version"] = self.version
        return stats, self.version, self.model.get_weights()

    def state_dict(self) -> dict[str, Any]:
        return {"policy_id": self.policy_id, "version": self.version, "ppo": self.ppo.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
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
