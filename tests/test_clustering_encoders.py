"""Clustering with the project's real (untrained) encoders on the toy tasks.

The equivariant encoder's group-pooled features are invariant, so a task and its rotated or
mirrored copies land on one policy, while different toy groups stay apart; the CNN twin's features
are not invariant, and it sees a transformed copy about as far away as another task group.

The encoders are untrained and as wide as ``NET`` (8/16/16/32 regular fields, 64 invariant
features): at the narrower default width an untrained encoder separates the toy groups only on
some seeds (docs/clustering.md has both ARI tables).
"""

from __future__ import annotations

import numpy as np
import pytest

from covers_dist.clustering import PolicyBank, normalize_pair, wasserstein1
from covers_dist.bench.toy_stream import encoder_features, run_toy_stream, toy_initial_obs, toy_stream
from covers_dist.config import DEFAULT_THRESHOLDS, ClusteringConfig, NetworkConfig
from covers_dist.envs.toy import TOY_TASKS
from covers_dist.symmetry import D4_ELEMENTS

D_EPS = DEFAULT_THRESHOLDS["wasserstein"]
NORM = ClusteringConfig().feature_norm
EPISODES = ClusteringConfig().update_every
NET = NetworkConfig(channels=[8, 16, 16, 32], hidden=64)


def _w1(fn, o, b) -> float:
    return wasserstein1(*normalize_pair(fn(0, o), fn(0, b), NORM))


def _distances(kind: str) -> dict[str, np.ndarray]:
    """W1 (buffer units) from a buffer of 32 reset frames of each base task T to:
    the same 8 resets seen through each g ("same_state", 3 x 8), 8 fresh resets of each g.T
    ("transformed", 3 x 8), and 8 fresh resets of each g.T' of the other groups ("other", 3 x 16)."""
    fn = encoder_features(kind, "shared", seed=0, net_cfg=NET)
    fresh = {(t, g.name): toy_initial_obs(t, g.name, 8, seed=500 + 50 * i) for i, t in enumerate(TOY_TASKS) for g in D4_ELEMENTS}
    out: dict[str, list[list[float]]] = {"same_state": [], "transformed": [], "other": []}
    for t in TOY_TASKS:
        buffer = toy_initial_obs(t, "e", 32, seed=100)
        base = toy_initial_obs(t, "e", 8, seed=300)
        out["same_state"].append([_w1(fn, toy_initial_obs(t, g.name, 8, seed=300), base) for g in D4_ELEMENTS])
        out["transformed"].append([_w1(fn, fresh[t, g.name], buffer) for g in D4_ELEMENTS])
        out["other"].append([_w1(fn, fresh[u, g.name], buffer) for u in TOY_TASKS if u != t for g in D4_ELEMENTS])
    return {k: np.array(v) for k, v in out.items()}


@pytest.fixture(scope="module")
def equivariant_distances():
    return _distances("equivariant")


@pytest.fixture(scope="module")
def cnn_distances():
    return _distances("cnn")


def test_equivariant_features_recognize_transformed_copies(equivariant_distances):
    d = equivariant_distances
    assert d["same_state"].max() < 1e-3 * D_EPS  # invariance: g.T looks exactly like T
    assert d["transformed"].max() < D_EPS  # fresh episodes of any g.T are recalled to T's policy
    assert d["other"].min() > D_EPS  # another group is never recalled
    assert np.median(d["other"]) > 1.5 * D_EPS


def test_cnn_twin_does_not_recognize_transformed_copies(cnn_distances, equivariant_distances):
    d = cnn_distances
    moved = d["same_state"][:, 1:]  # the identity is excluded: same frames, distance 0
    assert np.all(d["same_state"][:, 0] == 0.0)
    assert moved.min() > 100 * equivariant_distances["same_state"].max()
    # to the CNN, the same states seen rotated or mirrored are about as far as another task group
    assert np.median(moved) > 0.9 * np.median(d["other"])
    assert d["transformed"].max() > d["other"].min()


def test_toy_stream_ari_with_untrained_equivariant_encoders():
    # 3 groups x 8 elements in random order, 2 batches of update_every episodes; each policy its own encoder
    row = run_toy_stream("wasserstein", "equivariant", D_EPS, NORM, "own", seed=0, episodes_per_batch=EPISODES, net_cfg=NET)
    assert row["episodes"] == 3 * 8 * 2 * EPISODES
    assert row["ari"] >= 0.9, row
    counts = np.array(row["confusion"]["counts"])
    assert len(set(counts.argmax(axis=0))) == 3  # each group's episodes mostly on a different policy


def test_toy_stream_cnn_is_deterministic():
    a = run_toy_stream("wasserstein", "cnn", D_EPS, NORM, "own", seed=3, batches_per_task=1, net_cfg=NET)
    b = run_toy_stream("wasserstein", "cnn", D_EPS, NORM, "own", seed=3, batches_per_task=1, net_cfg=NET)
    assert (a["ari"], a["confusion"], a["policies"]) == (b["ari"], b["confusion"], b["policies"])


def test_ground_truth_mode_on_the_toy_stream():
    bank = PolicyBank(None, mode="ground_truth")
    for obs, group, _ in toy_stream(seed=1, batches_per_task=1):
        bank.assign(obs, group_ids=group)
    assert len(bank) == 3 and bank.metrics()["ari"] == 1.0
