"""Shared by the API tests: a real clustering service filled with real toy-task episodes."""

from __future__ import annotations

import numpy as np
import torch

from covers_dist.config import Config, load_config
from covers_dist.envs import suite_layout
from covers_dist.envs.toy import ToyTask
from covers_dist.models import build_actor_critic
from covers_dist.runtime.clustering_service import ClusteringService
from covers_dist.runtime.learner import policy_seed

SMOKE = "configs/smoke.yaml"


def smoke_config(*overrides: str) -> Config:
    return load_config(SMOKE, list(overrides))


def initial_obs(cfg: Config, task: str, g: str, seeds: list[int]) -> dict[str, np.ndarray]:
    """First observations of toy episodes of ``g.task`` (one per seed)."""
    env = ToyTask(task, g, image_size=cfg.env.image_size, max_episode_steps=cfg.env.max_episode_steps)
    frames = [env.reset(seed=s)[0] for s in seeds]
    return {
        "image": np.stack([f["image"] for f in frames]),
        "proprio": np.stack([f["proprio"] for f in frames]).astype(np.float32),
    }


def policy_weights(cfg: Config, policy_id: int) -> dict[str, torch.Tensor]:
    """The initial weights the runtime gives policy ``policy_id``."""
    torch.manual_seed(policy_seed(cfg.seed, policy_id))
    return build_actor_critic(cfg.network, suite_layout(cfg.env.suite, cfg.env.image_size)).get_weights()


def filled_service(cfg: Config, stream: list[tuple[str, str]], episodes: int = 4) -> ClusteringService:
    """A clustering service after one assignment per (task, g) of ``stream``, as a run makes them."""
    service = ClusteringService(cfg)
    weights = {0: (1, policy_weights(cfg, 0))}
    next_episode = 0
    for it, (task, g) in enumerate(stream):
        idx = list(range(next_episode, next_episode + episodes))
        obs = initial_obs(cfg, task, g, idx)
        gid = list(cfg.env.tasks).index(task)
        record = service.assign(it, obs, idx, [gid] * episodes, weights)
        pid = int(record["policy_id"])
        if pid not in weights:
            weights[pid] = (1, policy_weights(cfg, pid))
            service.sync_weights({pid: weights[pid]})
        summaries = [
            {"episode_index": i, "policy_id": pid, "assigned_policy": pid, "success": float(i % 2), "return": 10.0 + i}
            for i in idx
        ]
        service.record_episodes(summaries)
        next_episode += episodes
        service.report(
            {
                "iteration": it + 1,
                "episodes": next_episode,
                "env_steps": next_episode * cfg.env.max_episode_steps,
                "wall_time": 1000.0 + it,
                f"success/{task}": 0.5,
                f"return/{task}": 12.5,
                "ari": float("nan"),
            }
        )
    return service


# ---- servers and clients ---------------------------------------------------------------------------
STREAM = [("reach", "e"), ("push", "r"), ("reach", "r2"), ("avoid", "f"), ("push", "rf")]


def api_config(*overrides: str) -> Config:
    """The smoke config with settings that make several policies and small request limits."""
    base = ("clustering.threshold=0.1", "api.refresh_s=0.1", "api.max_body_bytes=200000", "api.max_batch=8")
    return smoke_config(*base, *overrides)


def obs_batch_json(obs: dict[str, np.ndarray], png: bool = True) -> list[dict]:
    from covers_dist.api import observation_json

    return [observation_json(obs["image"][i], obs["proprio"][i], png=png) for i in range(len(obs["image"]))]


def wait_until(predicate, timeout_s: float = 10.0, every_s: float = 0.05):  # noqa: ANN001, ANN201
    """Poll ``predicate()`` until it returns something truthy (returned), or fail."""
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout_s} s")
        time.sleep(every_s)
