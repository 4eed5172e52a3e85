"""A stream of toy episodes for measuring clustering (ARI) with real, untrained encoders.

The stream visits every (task group, D4 element) pair of the toy suite once, in a seeded random
order; each visit yields ``batches_per_task`` assignment batches of ``episodes_per_batch``
episodes, of which the bank sees the first ``k`` observations (``k = 1``: the reset frame; the
toy tasks' initial frames do not depend on the policy). Encoders are the project's actor-critics
(``covers_dist.models.build_actor_critic``), untrained: ``own`` builds one per policy id (seeded
by the id, as a fresh policy would be), ``shared`` one frozen encoder for all.

The models (and with them torch) are imported inside the functions: importing this module stays
light.
"""

from __future__ import annotations

import time
from typing import Any, Iterator

import numpy as np

from ..clustering.bank import PolicyBank
from ..clustering.features import FeatureFn, SharedFeatures, color_histogram
from ..envs.toy import TOY_TASKS, ToyTask, toy_layout
from ..symmetry import D4_ELEMENTS

__all__ = ["toy_initial_obs", "toy_stream", "encoder_features", "run_toy_stream"]


def toy_initial_obs(task: str, g: str, episodes: int, seed: int, image_size: int = 32) -> dict[str, np.ndarray]:
    """Reset frames of ``episodes`` episodes of the toy task ``g.T`` (reset seeds ``seed + i``)."""
    env = ToyTask(task, g, image_size=image_size)
    frames = [env.reset(seed=seed + i)[0] for i in range(episodes)]
    return {"image": np.stack([f["image"] for f in frames]), "proprio": np.stack([f["proprio"] for f in frames])}


def toy_stream(
    seed: int = 0,
    batches_per_task: int = 2,
    episodes_per_batch: int = 8,
    image_size: int = 32,
    tasks: tuple[str, ...] = TOY_TASKS,
) -> Iterator[tuple[dict[str, np.ndarray], int, str]]:
    """Yield (first observations of a batch, true group id, element name), tasks in random order."""
    rng = np.random.default_rng(seed)
    pairs = [(gi, g.name) for gi in range(len(tasks)) for g in D4_ELEMENTS]
    for visit, idx in enumerate(rng.permutation(len(pairs))):
        group, g = pairs[idx]
        for b in range(batches_per_task):
            reset_seed = 1_000_000 * (seed + 1) + 10_000 * visit + episodes_per_batch * b
            yield toy_initial_obs(tasks[group], g, episodes_per_batch, reset_seed, image_size), group, g


def encoder_features(kind: str, source: str = "own", image_size: int = 32, seed: int = 0, net_cfg: Any = None) -> FeatureFn:
    """Features of untrained ``kind`` ("equivariant" | "cnn") actor-critics, as a FeatureFn."""
    from ..config import NetworkConfig
    from ..models import build_actor_critic

    net_cfg = net_cfg or NetworkConfig()
    layout = toy_layout(image_size)
    if source == "colors":
        return SharedFeatures(color_histogram)
    if source == "shared":
        model = build_actor_critic(net_cfg, layout, kind=kind, seed=seed).eval()
        return SharedFeatures(model.features_np)
    if source != "own":
        raise ValueError(f"feature source must be 'own', 'shared' or 'colors', got {source!r}")
    models: dict[int, Any] = {}

    def own(policy_id: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        if policy_id not in models:
            models[policy_id] = build_actor_critic(net_cfg, layout, kind=kind, seed=seed + policy_id).eval()
        return models[policy_id].features_np(obs)

    return own


def run_toy_stream(
    metric: str,
    kind: str,
    threshold: float,
    feature_norm: str = "buffer",
    source: str = "own",
    seed: int = 0,
    batches_per_task: int = 2,
    episodes_per_batch: int = 8,
    buffer_size: int = 128,
    net_cfg: Any = None,
) -> dict[str, Any]:
    """Cluster the toy stream with a fresh bank; returns ARI, policies made and timing.

    ``net_cfg`` (a :class:`covers_dist.config.NetworkConfig`; default: the defaults) shapes the
    untrained encoders.
    """
    features = encoder_features(kind, source, seed=seed, net_cfg=net_cfg)
    bank = PolicyBank(
        features, metric=metric, threshold=threshold, buffer_size=buffer_size, feature_norm=feature_norm, seed=seed
    )
    t0 = time.perf_counter()
    for obs, group, _ in toy_stream(seed, batches_per_task, episodes_per_batch):
        bank.assign(obs, group_ids=group)
    m = bank.metrics()
    return {
        "metric": metric,
        "kind": kind,
        "source": source,
        "feature_norm": feature_norm,
        "threshold": threshold,
        "seed": seed,
        "ari": m["ari"],
        "policies": len(bank),
        "episodes": m["episodes_labelled"],
        "confusion": m["confusion"],
        "seconds": round(time.perf_counter() - t0, 2),
        "median_assign_ms": float(np.median([r.wall_time_ms for r in bank.history])),
    }
