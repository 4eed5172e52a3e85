"""Distances, buffers, the assignment rule and the metrics, on synthetic features."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from scipy.stats import wasserstein_distance
from sklearn.metrics import adjusted_rand_score

from covers_dist.clustering import (
    AssignmentRecord,
    ObservationBuffer,
    PolicyBank,
    SharedFeatures,
    adjusted_rand_index,
    confusion_table,
    decide,
    get_distance,
    mahalanobis,
    mean_euclidean,
    normalize_pair,
    policy_counts,
    wasserstein1,
)
from covers_dist.config import load_config


# ---- distances ---------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(5))
def test_w1_matches_scipy_in_1d(seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(int(rng.integers(3, 30)), 1))
    b = rng.exponential(size=(int(rng.integers(3, 30)), 1)) + 0.5
    assert wasserstein1(a, b) == pytest.approx(wasserstein_distance(a[:, 0], b[:, 0]), abs=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_w1_matches_brute_force_over_permutations(seed):
    # equal-size uniform sets: an optimal coupling is a permutation (Birkhoff), so W1 = min mean cost
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(6, 3)), rng.normal(size=(6, 3)) + 0.3
    cost = np.linalg.norm(a[:, None] - b[None], axis=-1)
    best = min(cost[np.arange(6), list(p)].mean() for p in itertools.permutations(range(6)))
    assert wasserstein1(a, b) == pytest.approx(best, abs=1e-9)


@pytest.mark.parametrize("name", ["wasserstein", "euclidean", "mahalanobis"])
def test_identical_sets_give_zero(name):
    x = np.random.default_rng(1).normal(size=(20, 8))
    assert get_distance(name)(x, x.copy()) == pytest.approx(0.0, abs=1e-9)


def test_shifted_set_gives_the_shift():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(40, 5))
    shift = np.array([0.3, -1.2, 0.0, 2.0, 0.5])
    assert wasserstein1(x + shift, x) == pytest.approx(np.linalg.norm(shift), rel=1e-9)
    assert mean_euclidean(x + shift, x) == pytest.approx(np.linalg.norm(shift), rel=1e-9)


def test_w1_matches_pot_on_the_euclidean_cost():
    import ot

    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(30, 16)), rng.normal(size=(45, 16)) + 0.2
    ref = ot.emd2(np.full(30, 1 / 30), np.full(45, 1 / 45), ot.dist(a, b, metric="euclidean"))
    assert wasserstein1(a, b) == pytest.approx(ref, rel=1e-7)


def test_w1_is_not_squared_euclidean():
    # one point each, 3 apart: W1 is 3 (POT's default metric would give 9)
    assert wasserstein1(np.zeros((1, 2)), np.array([[3.0, 0.0]])) == pytest.approx(3.0)


def test_mahalanobis_known_case():
    # B's biased covariance is 0.5 I (isotropic, so shrinkage keeps it); ridge adds 1e-3 * 0.5
    b = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    expected = 3.0 / np.sqrt(0.5 * (1 + 1e-3) + 1e-8)
    assert mahalanobis(np.array([[3.0, 0.0]]), b) == pytest.approx(expected, rel=1e-9)


def test_mahalanobis_invariant_to_rotation_and_scale():
    rng = np.random.default_rng(3)
    b = rng.normal(size=(50, 4)) * np.array([1.0, 2.0, 0.5, 3.0])
    o = rng.normal(size=(10, 4)) + 1.0
    q, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    assert mahalanobis(7.0 * o @ q, 7.0 * b @ q) == pytest.approx(mahalanobis(o, b), rel=1e-7)


def test_mahalanobis_degenerate_buffers_stay_finite():
    o = np.ones((3, 16))
    one_point = np.zeros((1, 16))
    same_points = np.zeros((10, 16))
    for b in (one_point, same_points):
        d = mahalanobis(o, b)
        assert np.isfinite(d) and d > 1e3
    assert mahalanobis(np.zeros((2, 16)), same_points) == 0.0
    # fewer points than dimensions: still finite and positive
    rng = np.random.default_rng(4)
    assert 0 < mahalanobis(rng.normal(size=(3, 64)) + 1, rng.normal(size=(5, 64))) < np.inf


@pytest.mark.parametrize(
    "a, b, err, match",
    [
        (np.zeros((3,)), np.zeros((3, 2)), ValueError, "shape"),
        (np.zeros((0, 2)), np.zeros((3, 2)), ValueError, "shape"),
        (np.zeros((3, 2)), np.zeros((3, 4)), ValueError, "widths differ"),
        (np.full((3, 2), np.nan), np.zeros((3, 2)), ValueError, "NaN"),
        ([[0.0, 1.0]], np.zeros((3, 2)), TypeError, "numpy array"),
    ],
)
@pytest.mark.parametrize("name", ["wasserstein", "euclidean", "mahalanobis"])
def test_distance_input_errors(name, a, b, err, match):
    with pytest.raises(err, match=match):
        get_distance(name)(a, b)


def test_unknown_metric():
    with pytest.raises(ValueError, match="unknown clustering metric 'cosine'"):
        get_distance("cosine")


# ---- buffers -----------------------------------------------------------------------------------
def _obs(proprio: np.ndarray, size: int = 4) -> dict[str, np.ndarray]:
    n = proprio.shape[0]
    image = (np.arange(n, dtype=np.int64)[:, None, None, None] % 256 * np.ones((1, size, size, 3))).astype(np.uint8)
    return {"image": image, "proprio": proprio.astype(np.float32)}


def test_fifo_keeps_the_most_recent_frames():
    buf = ObservationBuffer(5, "fifo")
    buf.add(_obs(np.arange(12, dtype=float)[:, None]))
    assert len(buf) == 5 and buf.seen == 12
    assert sorted(buf.observations()["proprio"][:, 0]) == [7, 8, 9, 10, 11]


def test_reservoir_is_uniform_and_seeded():
    hits = np.zeros(100)
    for seed in range(400):
        buf = ObservationBuffer(10, "reservoir", seed=seed)
        for start in range(0, 100, 7):  # offered in uneven batches
            buf.add(_obs(np.arange(start, min(start + 7, 100), dtype=float)[:, None]))
        assert len(buf) == 10
        kept = buf.observations()["proprio"][:, 0].astype(int)
        assert len(set(kept)) == 10
        hits[kept] += 1
    # every frame is kept with probability 10/100 (40 expected hits in 400 runs; sd about 6)
    assert hits.min() > 15 and hits.max() < 70
    early, late = hits[:50].sum(), hits[50:].sum()
    assert abs(early - late) < 0.15 * (early + late)
    a, b = ObservationBuffer(10, seed=3), ObservationBuffer(10, seed=3)
    for buf in (a, b):
        buf.add(_obs(np.arange(50, dtype=float)[:, None]))
    np.testing.assert_array_equal(a.observations()["proprio"], b.observations()["proprio"])


def test_buffer_rejects_bad_input():
    with pytest.raises(ValueError, match="capacity"):
        ObservationBuffer(0)
    with pytest.raises(ValueError, match="replacement rule"):
        ObservationBuffer(4, "lru")
    buf = ObservationBuffer(4)
    with pytest.raises(TypeError, match="keys"):
        buf.add({"image": np.zeros((1, 4, 4, 3), np.uint8)})
    with pytest.raises(ValueError, match="uint8"):
        buf.add({"image": np.zeros((1, 4, 4, 3)), "proprio": np.zeros((1, 2), np.float32)})
    with pytest.raises(ValueError, match="frames but proprio"):
        buf.add({"image": np.zeros((2, 4, 4, 3), np.uint8), "proprio": np.zeros((1, 2), np.float32)})
    buf.add(_obs(np.zeros((2, 2))))
    with pytest.raises(ValueError, match="differ from the buffer"):
        buf.add(_obs(np.zeros((2, 3))))


# ---- the assignment rule -----------------------------------------------------------------------
def test_decide_rule():
    assert decide({}, 1.0, 4) == (None, "adopt")
    assert decide({0: 2.0, 1: 0.4}, 1.0, 4) == (1, "recall")
    assert decide({0: 1.0}, 1.0, 4) == (0, "recall")  # d == threshold recalls (new only when d > d_eps)
    assert decide({0: 2.0, 1: 1.5}, 1.0, 4) == (None, "new")
    assert decide({0: 2.0, 1: 1.5}, 1.0, 2) == (1, "recall_at_cap")
    assert decide({3: 0.5, 1: 0.5}, 1.0, 4) == (1, "recall")  # ties: lowest id


CENTRES = {0: 0.0, 1: 10.0, 2: -10.0}


def _cluster(rng: np.random.Generator, group: int, n: int = 4, dim: int = 6) -> dict[str, np.ndarray]:
    return _obs(rng.normal(scale=0.3, size=(n, dim)) + CENTRES[group])


def _bank(**kw) -> PolicyBank:
    kw.setdefault("threshold", 2.0)
    kw.setdefault("buffer_size", 16)
    kw.setdefault("feature_norm", "none")
    return PolicyBank(SharedFeatures(lambda obs: obs["proprio"]), **kw)


@pytest.mark.parametrize("metric", ["wasserstein", "euclidean", "mahalanobis"])
def test_new_versus_recall_on_clustered_features(metric):
    rng = np.random.default_rng(0)
    bank = _bank(metric=metric, threshold={"wasserstein": 2.0, "euclidean": 1.0, "mahalanobis": 10.0}[metric])
    stream = [0, 0, 1, 1, 0, 2, 1, 2, 0]
    records = [bank.assign(_cluster(rng, g), group_ids=g) for g in stream]
    assert [r.decision for r in records] == ["adopt", "recall", "new", "recall", "recall", "new", "recall", "recall", "recall"]
    assert [r.policy_id for r in records] == [0, 0, 1, 1, 0, 2, 1, 2, 0]
    assert records[0].distances == {} and records[0].new
    assert set(records[-1].distances) == {0, 1, 2}
    assert records[-1].distances[0] < records[-1].threshold < min(records[-1].distances[1], records[-1].distances[2])
    assert bank.current_policy_id == 0
    assert bank.metrics()["ari"] == 1.0
    assert [r.episode_indices for r in records[:2]] == [[0, 1, 2, 3], [4, 5, 6, 7]]
    assert all(r.metric == metric and r.num_observations == 4 and r.wall_time_ms >= 0 for r in records)


def test_max_policies_recalls_the_nearest():
    rng = np.random.default_rng(1)
    bank = _bank(max_policies=2)
    bank.assign(_cluster(rng, 0))
    bank.assign(_cluster(rng, 1))
    r = bank.assign(_obs(rng.normal(scale=0.3, size=(4, 6)) + 7.0))  # nearer to group 1 (10) than 0
    assert (r.decision, r.policy_id, r.new, len(bank)) == ("recall_at_cap", 1, False, 2)
    assert r.nearest_distance == r.distances[1] > r.threshold


def test_what_if_restricted_to_some_policies_keeps_the_banks_ids_and_cap():
    """A what-if compared with some policies only: a "new" gets the id after the bank's largest (not
    one of the left-out policies'), and the bank's own size decides recall_at_cap."""
    rng = np.random.default_rng(3)
    bank = _bank(max_policies=4)
    for g in (0, 1, 2):
        bank.assign(_cluster(rng, g), group_ids=g)
    far = _cluster(rng, 2)  # only group 2's policy is near: it is left out below
    r = bank.what_if(far, policies=[0, 1])
    assert (r.decision, r.policy_id, sorted(r.distances)) == ("new", 3, [0, 1])
    bank.max_policies = 3
    r = bank.what_if(far, policies=[0, 1])
    assert r.decision == "recall_at_cap" and r.policy_id in (0, 1)
    assert bank.what_if(far).decision == "recall"
    with pytest.raises(LookupError, match="none of the policies"):
        bank.what_if(far, policies=[9])


def test_what_if_changes_nothing():
    rng = np.random.default_rng(2)
    bank = _bank(replacement="reservoir", buffer_size=4)
    for g in (0, 1, 0):
        bank.assign(_cluster(rng, g), group_ids=g)
    before = json.dumps(bank.summary(), sort_keys=True)
    rng_state = bank.entries[0].buffer.rng.bit_generator.state
    frames = bank.entries[0].buffer.observations()["proprio"].copy()
    obs = _cluster(rng, 0)
    preview = bank.what_if(obs, group_ids=0)
    assert json.dumps(bank.summary(), sort_keys=True) == before
    assert bank.entries[0].buffer.rng.bit_generator.state == rng_state
    np.testing.assert_array_equal(bank.entries[0].buffer.observations()["proprio"], frames)
    actual = bank.assign(obs, group_ids=0)
    keep = ("policy_id", "decision", "new", "distances", "episode_indices", "true_groups")
    assert {k: getattr(preview, k) for k in keep} == {k: getattr(actual, k) for k in keep}
    assert _bank().what_if(obs).decision == "adopt"


def test_own_encoder_features_per_policy():
    calls = []

    def feature_fn(policy_id, obs):  # each policy's "encoder" scales the features differently
        calls.append((policy_id, obs["image"].shape[0]))
        return obs["proprio"] * (policy_id + 1)

    rng = np.random.default_rng(3)
    bank = PolicyBank(feature_fn, threshold=1.0, buffer_size=8, feature_norm="none")
    bank.assign(_cluster(rng, 0))
    bank.assign(_cluster(rng, 1))
    calls.clear()
    obs = _obs(np.full((4, 6), 3.0))
    d = bank.distances(obs)
    assert calls == [(0, 8), (1, 8)]  # O and B_i encoded together by policy i's own encoder
    for pid in (0, 1):
        buf = bank.entries[pid].buffer.observations()
        assert d[pid] == pytest.approx((pid + 1) * wasserstein1(obs["proprio"], buf["proprio"]))


def test_feature_fn_output_is_checked():
    bank = PolicyBank(lambda pid, obs: obs["proprio"][:1], buffer_size=4)
    rng = np.random.default_rng(0)
    bank.assign(_cluster(rng, 0))
    with pytest.raises(ValueError, match="feature function for policy 0 returned shape"):
        bank.assign(_cluster(rng, 0))
    with pytest.raises(ValueError, match="no feature_fn"):
        b = PolicyBank(None)
        b.assign(_cluster(rng, 0))
        b.assign(_cluster(rng, 0))


@pytest.mark.parametrize("norm", ["l2", "buffer"])
def test_feature_norms_make_distances_scale_free(norm):
    rng = np.random.default_rng(5)
    a, b = _cluster(rng, 0), _obs(rng.normal(size=(4, 6)) + 1.0)
    d = []
    for scale in (1.0, 1000.0):
        bank = PolicyBank(SharedFeatures(lambda o, s=scale: o["proprio"] * s), feature_norm=norm)
        bank.assign(a)
        d.append(bank.what_if(b).distances[0])
    assert d[0] == pytest.approx(d[1]) and d[0] > 0


def test_buffer_norm_units_by_hand():
    # B = {0, 2} on a line: mean pairwise distance 2; O = {5}: W1 = mean(5, 3) = 4 -> 4 / 2 = 2
    assert normalize_pair(np.array([[5.0]]), np.array([[0.0], [2.0]]), "buffer")[0][0, 0] == 2.5
    bank = PolicyBank(SharedFeatures(lambda o: o["proprio"].astype(np.float64)), feature_norm="buffer")
    bank.assign(_obs(np.array([[0.0], [2.0]])))
    assert bank.what_if(_obs(np.array([[5.0], [5.0]]))).distances[0] == pytest.approx(2.0)
    # a buffer of one point: the spread of O and B together is the unit
    one = PolicyBank(SharedFeatures(lambda o: o["proprio"].astype(np.float64)), feature_norm="buffer")
    one.assign(_obs(np.array([[0.0]])))
    assert one.what_if(_obs(np.array([[3.0]]))).distances[0] == pytest.approx(1.0)
    assert one.what_if(_obs(np.array([[0.0]]))).distances[0] == 0.0
    with pytest.raises(ValueError, match="feature_norm"):
        normalize_pair(np.zeros((1, 1)), np.zeros((1, 1)), "unit")


def test_episode_and_group_validation():
    rng = np.random.default_rng(6)
    bank = _bank(initial_frames=2)
    with pytest.raises(ValueError, match="not a multiple of initial_frames=2"):
        bank.assign(_obs(np.zeros((3, 6))))
    assert bank.what_if(_obs(np.zeros((3, 6)))).decision == "adopt"  # a query takes any number of frames
    r = bank.assign(_obs(np.zeros((4, 6))), group_ids=[0, 1])
    assert r.episode_indices == [0, 1] and r.true_groups == [0, 1]
    with pytest.raises(ValueError, match="already assigned"):
        bank.assign(_cluster(rng, 0), episode_indices=[1, 2])
    with pytest.raises(ValueError, match="duplicates"):
        bank.assign(_cluster(rng, 0), episode_indices=[5, 5])
    with pytest.raises(ValueError, match="cannot be split evenly"):
        bank.assign(_obs(np.zeros((5, 6))), episode_indices=[5, 6])
    with pytest.raises(ValueError, match="differ from the bank's"):
        bank.assign(_obs(np.zeros((2, 5))))
    assert len(bank.history) == 1 and len(bank) == 1
    with pytest.raises(ValueError, match="group_ids has 3 entries for 2 episodes"):
        bank.assign(_cluster(rng, 0), episode_indices=[5, 6], group_ids=[0, 0, 0])
    for kw, match in [({"threshold": 0}, "threshold"), ({"metric": "l1"}, "metric"), ({"mode": "oracle"}, "mode"),
                      ({"buffer_size": 0}, "buffer_size"), ({"feature_norm": "l1"}, "feature_norm")]:
        with pytest.raises(ValueError, match=match):
            PolicyBank(None, **kw)


def test_ground_truth_mode():
    rng = np.random.default_rng(7)
    bank = _bank(mode="ground_truth", max_policies=3)
    with pytest.raises(ValueError, match="needs group_ids"):
        bank.assign(_cluster(rng, 0))
    records = [bank.assign(_cluster(rng, 0), group_ids=g) for g in (5, 5, 9, 5, 9)]  # features say nothing
    assert [(r.decision, r.policy_id) for r in records] == [("adopt", 0), ("recall", 0), ("new", 1), ("recall", 0), ("recall", 1)]
    assert all(r.distances == {} and r.mode == "ground_truth" for r in records)
    r = bank.assign(_cluster(rng, 0), group_ids=[9, 5, 5, 9])  # tie: the latest episode's group (9)
    assert r.policy_id == 1
    bank.assign(_cluster(rng, 0), group_ids=7)
    capped = bank.assign(_cluster(rng, 0), group_ids=8)
    assert (capped.decision, capped.policy_id) == ("recall_at_cap", 2)
    assert bank.metrics()["ari"] == pytest.approx(adjusted_rand_score(*reversed(bank.label_pairs())))


def test_from_config_thresholds_and_mode():
    bank = PolicyBank.from_config(load_config(overrides=["clustering.metric=mahalanobis"]))
    assert (bank.metric, bank.threshold, bank.mode, bank.buffer_size) == ("mahalanobis", 10.0, "distance", 128)
    cfg = load_config(overrides=["runtime.method=covers-gt", "clustering.threshold=0.25"])
    bank = PolicyBank.from_config(cfg)
    assert (bank.threshold, bank.mode) == (0.25, "ground_truth")


def test_same_seed_same_assignments():
    def run():
        rng = np.random.default_rng(11)
        bank = _bank(buffer_size=3)
        return [(r.policy_id, r.decision, r.distances) for r in (bank.assign(_cluster(rng, g)) for g in [0, 1, 0, 2, 1, 0, 0])]

    assert run() == run()


# ---- records and metrics -------------------------------------------------------------------------
def test_record_round_trips_through_json():
    rng = np.random.default_rng(8)
    bank = _bank()
    bank.assign(_cluster(rng, 0), group_ids=0)
    r = bank.assign(_cluster(rng, 1), group_ids=[1, 1, 1, 0])
    d = json.loads(json.dumps(r.to_dict(), allow_nan=False))
    assert d["distances"] == {"0": r.distances[0]} and d["num_episodes"] == 4 and d["decision"] == "new"
    assert AssignmentRecord.from_dict(d) == r


def test_metrics_against_sklearn_and_by_hand():
    assert adjusted_rand_index([0, 0, 0, 0], [0, 0, 1, 1]) == pytest.approx(0.0)
    assert adjusted_rand_index([3, 3, 7, 7], [1, 1, 0, 0]) == 1.0
    assert adjusted_rand_index([], []) is None
    rng = np.random.default_rng(9)
    for n, kp, kg in [(60, 4, 3), (7, 7, 2), (500, 9, 4), (3, 1, 3), (40, 40, 40)]:
        for _ in range(20):
            p, g = rng.integers(0, kp, n), rng.integers(0, kg, n)
            assert adjusted_rand_index(p, g) == pytest.approx(adjusted_rand_score(g, p), abs=1e-12), (p, g)
    # the degenerate partitions: one episode, every episode alone, all in one cluster
    for p, g in [([5], [2]), ([0, 1, 2], [2, 1, 0]), ([1, 1, 1], [0, 0, 0]), ([0, 1, 2], [0, 0, 0])]:
        assert adjusted_rand_index(p, g) == pytest.approx(adjusted_rand_score(g, p)), (p, g)
    big = np.repeat([0, 1], 50_000)  # 10^5 episodes: pair counts ~5e9 and their products ~1e19
    assert adjusted_rand_index(big, big[::-1]) == 1.0
    assert policy_counts([2, 0, 2]) == {0: 1, 2: 2}
    table = confusion_table([0, 0, 1, 1, 1], [5, 6, 6, 6, 5])
    assert table == {"policies": [0, 1], "groups": [5, 6], "counts": [[1, 1], [1, 2]]}
    with pytest.raises(ValueError, match="entries"):
        adjusted_rand_index([0, 1], [0])


def test_episode_stats_and_summary():
    rng = np.random.default_rng(10)
    bank = _bank()
    bank.assign(_cluster(rng, 0), group_ids=0)
    bank.assign(_cluster(rng, 1), group_ids=1)
    bank.record_episode_stats(1, success=1.0, ret=-3.5, group_id=1, episode_index=8)  # an in-between episode
    bank.record_episode_stats(0, success=np.float32(0.0), ret=-7.0, group_id=1, episode_index=2)  # already labelled
    with pytest.raises(ValueError, match="unknown policy_id 4"):
        bank.record_episode_stats(4, 1.0, 0.0)
    with pytest.raises(ValueError, match="ret must be a finite number"):
        bank.record_episode_stats(0, 1.0, float("nan"))
    s = json.loads(json.dumps(bank.summary(), allow_nan=False))
    p0, p1 = s["policies"]
    assert (p1["last_success"], p1["last_return"], p1["episodes_reported"]) == (1.0, -3.5, 1)
    assert p1["group_histogram"] == {"1": 5} and p0["group_histogram"] == {"0": 4}
    assert (p0["episodes_assigned"], p0["created_at_episode"], p1["created_at_episode"]) == (4, 0, 4)
    assert s["metrics"]["episodes_labelled"] == 9 and s["metrics"]["ari"] == 1.0
    assert s["metrics"]["confusion"]["counts"] == [[4, 0], [0, 5]]
    assert s["current_policy_id"] == 1 and s["num_policies"] == 2


def test_bench_assign_smoke(capsys):
    from covers_dist.cli import main

    args = ["bench", "assign", "--policies", "1,3", "--buffers", "8", "--repeats", "1", "--rollout-steps", "20", "--json"]
    assert main(args) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rows[0]["reference"] == "toy_rollout" and rows[0]["steps"] == 20
    cells = {(r["metric"], r["policies"]) for r in rows[1:]}
    assert cells == {(m, p) for m in ("wasserstein", "euclidean", "mahalanobis") for p in (1, 3)}
    assert all(r["median_ms"] > 0 and r["buffer_size"] == 8 for r in rows[1:])
