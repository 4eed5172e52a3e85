"""The rollout worker: steps several transformed tasks at once with one policy's weights.

A plain class (no Ray): :mod:`covers_dist.runtime.actors` turns it into a Ray actor, serial mode
uses it directly. A worker is told which (task, g) each episode runs in and which policy's
weights to use; it never tells the policy which task it is in. Episodes are seeded from their
global index, so a retried call (after a worker restart) returns exactly the same episodes.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..config import Config
from ..envs import make_task, suite_layout
from ..evaluation.episodes import run_eval_episodes
from ..evaluation.protocol import EvalJob, EvalPair
from ..models import build_actor_critic
from ..ppo.noise import coloured_entries, coloured_episode
from ..ppo.rollout import run_lockstep
from ..symmetry import GroupElement
from .ray_setup import resolve_weights

__all__ = [
    "EVAL_WORKER_INDEX",
    "EpisodeSpec",
    "RolloutWorker",
    "episode_seed",
    "merge_first_frames",
    "split_first_frames",
    "summarize_episode",
    "training_seeds",
]


@dataclass(frozen=True)
class EpisodeSpec:
    """What one episode runs in. ``group_id`` is for metrics only; the policy never sees it."""

    episode_index: int
    task: str
    g: str
    group_id: int


def training_seeds(base_seed: int, specs: list[EpisodeSpec]) -> list[int]:
    """The reset seeds of these training episodes (a pure function of their indices)."""
    return [episode_seed(base_seed, s.episode_index) for s in specs]


def _eval_specs(pair: EvalPair, n: int) -> list[EpisodeSpec]:
    return [EpisodeSpec(i, pair.task, pair.g, pair.group_id) for i in range(n)]


def episode_seed(base_seed: int, episode_index: int) -> int:
    """The seed of an episode: a pure function of the run seed and the episode's global index."""
    return int(np.random.SeedSequence([base_seed, episode_index]).generate_state(1)[0])


#: Worker index of evaluation workers (only used in their names and stats).
EVAL_WORKER_INDEX = 1000


def summarize_episode(ep: dict[str, Any]) -> dict[str, Any]:
    """The per-episode row the driver logs (no frames)."""
    return {
        "episode_index": int(ep["episode_index"]),
        "task": ep["task"],
        "g": ep["g"],
        "group_id": int(ep["group_id"]),
        "policy_id": int(ep["policy_id"]),
        "return": float(ep["reward"].sum()),
        "success": float(ep["success"].max()) if len(ep["success"]) else 0.0,
        "length": int(len(ep["reward"])),
    }


def split_first_frames(episodes: list[dict[str, Any]], k: int) -> tuple[list[dict], list[dict]]:
    """(first-k observations of each episode, summaries): all that leaves a worker for the driver."""
    firsts = [{"image": ep["image"][:k].copy(), "proprio": ep["proprio"][:k].copy()} for ep in episodes]
    return firsts, [summarize_episode(ep) for ep in episodes]


def merge_first_frames(parts: list[tuple[dict[str, np.ndarray], list[EpisodeSpec]]]) -> dict[str, np.ndarray]:
    """Per-worker first observations merged into one batch in episode order."""
    rows = sorted(
        ((s.episode_index, f["image"][i], f["proprio"][i]) for f, specs in parts for i, s in enumerate(specs)),
        key=lambda r: r[0],
    )
    return {"image": np.stack([r[1] for r in rows]), "proprio": np.stack([r[2] for r in rows])}


class RolloutWorker:
    """Runs batches of episodes with ``envs_per_worker`` environments stepped together."""

    def __init__(self, cfg: Config, worker_index: int = 0, max_cached_envs: int = 16) -> None:
        torch.set_num_threads(cfg.runtime.torch_threads)
        self.cfg = cfg
        self.worker_index = worker_index
        self.layout = suite_layout(cfg.env.suite, cfg.env.image_size)
        self.model = build_actor_critic(cfg.network, self.layout)
        self.noise_coloured = coloured_entries(cfg.ppo.noise_entries, self.layout.action_dim, self.layout.action_pairs)
        self.model.eval()
        self._loaded: tuple[int, int] | None = None  # (policy id, version) of the loaded weights
        self._envs: OrderedDict[tuple[str, int], Any] = OrderedDict()
        self._max_cached_envs = max_cached_envs
        self.weight_pulls = 0
        self.env_steps = 0

    # ---- weights -----------------------------------------------------------------------------
    def _ensure_weights(self, policy_id: int, version: int, weights: Any) -> None:
        if self._loaded == (policy_id, version):
            return
        self.model.set_weights(resolve_weights(weights))
        self.model.eval()
        self._loaded = (policy_id, version)
        self.weight_pulls += 1

    # ---- environments -------------------------------------------------------------------------
    def _env(self, task: str, g: str, slot: int) -> Any:
        """The env of ``slot`` for base task ``task``, switched to element ``g``: envs that can
        change their element in place (Meta-World: building one costs ~0.25 s) are kept per
        (task, slot), others are rebuilt when the element changes."""
        key = (task, slot)
        env = self._envs.get(key)
        if env is not None and getattr(getattr(env, "g", None), "name", None) != g:
            if hasattr(env, "set_element"):
                env.set_element(GroupElement.from_name(g))
            else:
                del self._envs[key]
                env.close()
                env = None
        if env is None:
            env = make_task(self.cfg.env, task, GroupElement.from_name(g))
            self._envs[key] = env
            while len(self._envs) > self._max_cached_envs:
                _, old = self._envs.popitem(last=False)
                old.close()
        else:
            self._envs.move_to_end(key)
        return env

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()

    # ---- sampling -----------------------------------------------------------------------------
    def sample(
        self,
        specs: list[EpisodeSpec],
        policy_id: int,
        version: int,
        weights: Any = None,
        deterministic: bool = False,
        seeds: list[int] | None = None,
        noise_beta: float | None = None,
    ) -> list[dict[str, Any]]:
        """Run one full episode per spec with the given policy; returns Episode dicts.

        ``seeds`` (one per spec) replaces the training seeds derived from the episode indices
        (evaluation uses its own seeds, see :mod:`covers_dist.evaluation.protocol`).
        ``noise_beta`` is the colour of the action noise (None: ``ppo.noise_beta``; the driver
        passes the policy's faded colour, ``ppo.noise_fade_success``).
        """
        if noise_beta is not None and not 0.0 <= noise_beta <= 2.0:
            raise ValueError(f"noise_beta must be in [0, 2], got {noise_beta!r}")
        beta = self.cfg.ppo.noise_beta if noise_beta is None else float(noise_beta)
        if seeds is not None and len(seeds) != len(specs):
            raise ValueError(f"need one seed per episode spec, got {len(seeds)} seeds for {len(specs)} specs")
        self._ensure_weights(policy_id, version, weights)
        episodes: list[dict[str, Any]] = []
        width = self.cfg.runtime.envs_per_worker
        for start in range(0, len(specs), width):
            chunk = None if seeds is None else [int(s) for s in seeds[start : start + width]]
            episodes.extend(
                self._run_group(specs[start : start + width], policy_id, version, deterministic, chunk, beta)
            )
        return episodes

    def first_observations(self, specs: list[EpisodeSpec], seeds: list[int]) -> dict[str, np.ndarray]:
        """The first observation of each spec's env reset with its seed (no policy involved)."""
        if len(seeds) != len(specs):
            raise ValueError(f"need one seed per episode spec, got {len(seeds)} seeds for {len(specs)} specs")
        obs = [self._env(s.task, s.g, 0).reset(seed=int(seed))[0] for s, seed in zip(specs, seeds)]
        return {"image": np.stack([o["image"] for o in obs]), "proprio": np.stack([o["proprio"] for o in obs])}

    def _run_group(
        self,
        specs: list[EpisodeSpec],
        policy_id: int,
        version: int,
        deterministic: bool,
        seeds: list[int] | None = None,
        noise_beta: float = 0.0,
    ) -> list[dict[str, Any]]:
        envs = [self._env(s.task, s.g, slot) for slot, s in enumerate(specs)]
        if seeds is None:
            seeds = training_seeds(self.cfg.seed, specs)
        gen = torch.Generator().manual_seed(int(seeds[0]) % (2**63))
        episodes = run_lockstep(
            self.model,
            envs,
            seeds,
            gen,
            deterministic,
            noise_beta=[noise_beta * coloured_episode(s.episode_index, self.cfg.ppo.noise_fraction) for s in specs],
            noise_steps=self.cfg.env.max_episode_steps,
            noise_coloured=self.noise_coloured,
        )
        for ep, spec in zip(episodes, specs):
            self.env_steps += len(ep["reward"])
            ep.update(
                task=spec.task,
                g=spec.g,
                group_id=spec.group_id,
                episode_index=spec.episode_index,
                policy_id=policy_id,
                policy_version=version,
            )
        return episodes

    # ---- evaluation (covers_dist.evaluation) ------------------------------------------------------
    def eval_first_frames(self, items: list[tuple[EvalPair, list[int]]]) -> list[dict[str, np.ndarray]]:
        """First observations of each (pair, seeds): what the bank chooses a policy from."""
        return [self.first_observations(_eval_specs(pair, len(seeds)), seeds) for pair, seeds in items]

    def eval_jobs(self, jobs: list[EvalJob], weights_map: dict[int, tuple[int, Any]]) -> list[dict[str, list[Any]]]:
        """Run every job's episodes with :func:`~covers_dist.evaluation.episodes.run_eval_episodes`;
        per job ``{"success": [...], "return": [...], "state_key": [...], "closest": [...]}`` (no
        frames; ``closest`` is None for episodes of envs that report no ``target_ratio``).

        ``weights_map`` is ``{policy id: (version, weights)}``; in this process a value may also be
        ``(version, policy)`` with a policy object (anything with ``act``, e.g.
        :class:`~covers_dist.evaluation.episodes.GreedyPolicy` around another framework's module),
        which then acts instead of this worker's network.
        """
        out = []
        width = self.cfg.runtime.envs_per_worker
        for job in jobs:
            version, handle = weights_map[job.policy_id]
            if hasattr(handle, "act"):
                policy = handle
            else:
                self._ensure_weights(job.policy_id, version, handle)
                policy = self.model
            deterministic = job.mode == "greedy"
            result: dict[str, list[Any]] = {"success": [], "return": [], "state_key": [], "closest": []}
            for start in range(0, len(job.seeds), width):
                seeds = [int(x) for x in job.seeds[start : start + width]]
                envs = [self._env(job.pair.task, job.pair.g, slot) for slot in range(len(seeds))]
                gen = torch.Generator().manual_seed(seeds[0] % (2**63))
                for ep in run_eval_episodes(policy, envs, seeds, deterministic, gen, self.layout):
                    self.env_steps += ep["length"]
                    result["success"].append(ep["success"])
                    result["return"].append(ep["return"])
                    result["state_key"].append(ep.get("state_key"))
                    result["closest"].append(ep.get("closest"))
            out.append(result)
        return out

    def probe(self) -> np.ndarray:
        """This process's :meth:`~covers_dist.models.ActorCritic.probe_outputs` (the cross-process check)."""
        return self.model.probe_outputs()

    def stats(self) -> dict[str, int]:
        return {"worker_index": self.worker_index, "env_steps": self.env_steps, "weight_pulls": self.weight_pulls}
