"""Clustering with the project's real (untrained) encoders on the toy tasks.

The equivariant encoder's group-pooled features are invariant, so a task and its rotated or
mirrored copies land on one policy, while different toy groups stay apart; the CNN twin's features
are not invariant, and it sees a transformed copy about as far away as another task group.

The encoders are untrained and as wide as ``NET`` (8/16/16/32 regular fields, 64 invariant
features): at the narrower default width an untrained encoder separates the toy groups only on
some seeds (docs/research/clustering.md has both ARI tables).
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


@pytest.mark.slow
def test_toy_stream_ari_with_untrained_equivariant_encoders():
    """Slow tier (half a minute on 2 cores: 48 batches through the bank): the default suite checks
    what the stream's ARI rests on, the distances above (every copy of a group under the threshold,
    other groups over it), and the bank's decisions on real frames (tests/test_smoke_run.py)."""
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


def test_color_histogram_is_exactly_invariant_and_checks_its_input():
    from covers_dist.clustering import color_histogram

    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(3, 32, 32, 3), dtype=np.uint8)
    base = color_histogram({"image": images})
    assert base.shape == (3, 64) and np.allclose((base**2).sum(axis=1), 1.0)
    for k in range(4):
        for flip in (False, True):
            moved = np.rot90(images, k, axes=(1, 2))
            moved = moved[:, :, ::-1] if flip else moved
            np.testing.assert_array_equal(color_histogram({"image": np.ascontiguousarray(moved)}), base)
    assert not np.allclose(color_histogram({"image": images[:, :, :, ::-1].copy()}), base)  # colours matter
    with pytest.raises(ValueError, match="uint8 frames of shape"):
        color_histogram({"image": images.astype(np.float32)})
    with pytest.raises(ValueError, match="levels must be an integer in 2..16"):
        color_histogram({"image": images}, levels=1)


def test_color_features_keep_the_four_meta_world_groups_apart_on_real_frames():
    """Initial frames of the four Meta-World groups under all of D4, rendered: the calibrated
    rule with colour-histogram features gives one policy per group on a stream that visits each
    group twice (8-frame batches, as in training)."""
    from covers_dist.clustering import SharedFeatures, adjusted_rand_index, color_histogram
    from covers_dist.config import load_config
    from covers_dist.envs.metaworld_suite import MetaWorldTask

    tasks = ["reach-v3", "button-press-topdown-v3", "drawer-close-v3", "plate-slide-v3"]
    frames = {}
    for k, task in enumerate(tasks):
        env = MetaWorldTask(task, image_size=64)
        obs = []
        for j, g in enumerate(D4_ELEMENTS):
            env.set_element(g)
            obs += [env.reset(seed=1000 * k + 10 * j + s)[0] for s in range(3)]
        env.close()
        frames[k] = {key: np.stack([o[key] for o in obs]) for key in ("image", "proprio")}
    cfg = load_config("quickstart", ["seed=0"])
    bank = PolicyBank.from_config(cfg, SharedFeatures(color_histogram))
    rng = np.random.default_rng(0)
    truth, policies = [], []
    for _ in range(2):
        for k in rng.permutation(len(tasks)):
            for _ in range(3):
                idx = rng.choice(len(frames[k]["image"]), size=8, replace=False)
                record = bank.assign({key: v[idx] for key, v in frames[k].items()})
                truth.append(int(k))
                policies.append(record.policy_id)
    assert len(set(policies)) == len(tasks)
    assert adjusted_rand_index(truth, policies) == pytest.approx(1.0)
