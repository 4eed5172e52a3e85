"""The calibrated decision rule (clustering.rule: calibrated): a per-policy permutation test.

Features come from a lookup, not a network: ``proprio[:, 0]`` holds the group id and
``proprio[:, 1]`` an instance id; the feature function maps (group, instance) to a fixed vector and
then applies a slowly drifting anisotropic rescaling and shift (the "encoder" at that moment),
the same for O and B_i, as a policy's own encoder does while it trains. The false-split rate and
power measurements (section g) read features from a fixed table of vectors of one distribution
per group instead (:class:`TableFeatures`).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from covers_dist.clustering import AssignmentRecord, CheckpointError, PolicyBank, load_bank, save_bank
from covers_dist.clustering import calibration
from covers_dist.clustering.calibration import NullDistance, max_draws, permutation_test
from covers_dist.clustering.distances import get_distance
from covers_dist.clustering.features import normalize_pair
from covers_dist.clustering.metrics import adjusted_rand_index
from covers_dist.config import ConfigError, config_from_dict, load_config

BATCH = 8


class DriftingFeatures:
    """A group's instances are a 2-D cloud: a 1-D mixture (weights 0.85/0.10/0.05 at 0, 1, 3, as
    tasks of one group an encoder partly tells apart) plus small noise; groups sit ``spacing``
    apart. ``step`` (advanced by the test between assignments) drifts the per-axis scale and the
    offset, identically for every frame encoded at that step."""

    def __init__(self, spacing: float = 50.0, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.spacing = spacing
        self.cache: dict[tuple[int, int], np.ndarray] = {}
        self.step = 0

    def base(self, group: int, instance: int) -> np.ndarray:
        key = (group, instance)
        if key not in self.cache:
            c = self.rng.choice(3, p=[0.85, 0.10, 0.05])
            x = float([0.0, 1.0, 3.0][c]) + 0.05 * self.rng.normal()
            self.cache[key] = np.array([x + self.spacing * group, 0.05 * self.rng.normal()])
        return self.cache[key]

    def __call__(self, policy_id: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        t = self.step
        z = np.stack([self.base(int(g), int(i)) for g, i in obs["proprio"][:, :2]])
        scale = np.array([math.exp(0.4 * math.sin(t / 9.0)), math.exp(0.8 * math.cos(t / 13.0))])
        return z * scale + np.array([0.03 * t, -0.02 * t])


class Stream:
    """Batches of BATCH fresh instances of a group."""

    def __init__(self) -> None:
        self.next_instance: dict[int, int] = {}

    def batch(self, group: int) -> dict[str, np.ndarray]:
        start = self.next_instance.get(group, 0)
        self.next_instance[group] = start + BATCH
        proprio = np.zeros((BATCH, 3), np.float32)
        proprio[:, 0] = group
        proprio[:, 1] = np.arange(start, start + BATCH)
        return {"image": np.zeros((BATCH, 8, 8, 3), np.uint8), "proprio": proprio}


def run_stream(bank: PolicyBank, feats: DriftingFeatures, groups: list[int]) -> list[AssignmentRecord]:
    stream = Stream()
    out = []
    for g in groups:
        out.append(bank.assign(stream.batch(g), group_ids=g))
        feats.step += 1
    return out


def stable(rec: AssignmentRecord) -> dict:
    d = rec.to_dict()
    d.pop("wall_time_ms")
    d.pop("time_unix")
    return d


# ---- (a) no false split under drift; the fixed threshold does split ----------------------------------
def test_one_group_with_drifting_features_threshold_splits_calibrated_does_not():
    feats = DriftingFeatures()
    thr = PolicyBank(feats, metric="wasserstein", threshold=1.0)
    recs = run_stream(thr, feats, [0] * 200)
    assert len(thr) >= 2, "the fixed threshold should split this one-group stream"
    assert max(r.nearest_distance for r in recs[1:]) > 1.0

    feats = DriftingFeatures()
    cal = PolicyBank(feats, metric="wasserstein", threshold=1.0, rule="calibrated", calibration_samples=50)
    recs = run_stream(cal, feats, [0] * 120)
    assert len(cal) == 1
    assert [r.decision for r in recs] == ["adopt"] + ["recall"] * 119
    # the threshold alone would have split it: some observed distance exceeds d_eps
    assert any(r.nearest_distance > 1.0 for r in recs[2:])
    # the second batch meets an 8-frame buffer: the pooled test (C(16, 8) splits) runs there too
    assert all(r.p_values[0] is not None and r.calibration["fallback"] == [] for r in recs[1:])
    assert all(r.calibration["policies"]["0"]["tested"] for r in recs[1:])
    json.dumps([r.to_dict() for r in recs])


# ---- (b) different groups are still separated ------------------------------------------------------
def test_separates_well_separated_groups():
    feats = DriftingFeatures()
    order = list(np.random.default_rng(3).permutation([0, 1, 2] * 8))
    bank = PolicyBank(
        feats, metric="wasserstein", rule="calibrated", false_split_rate=0.01, calibration_samples=50, seed=1
    )
    recs = run_stream(bank, feats, [int(g) for g in order])
    assert len(bank) == 3
    assert adjusted_rand_index(*bank.label_pairs()) == 1.0
    assert sum(r.decision == "new" for r in recs) == 2
    for r in recs:  # a new policy only when every policy rejected (or, on a tiny buffer, the threshold did)
        if r.decision == "new":
            assert r.calibration["accepted"] == []
            assert all(p is None or p <= 0.01 for p in r.p_values.values())
        elif r.decision == "recall":
            assert r.policy_id in r.calibration["accepted"]


def test_every_policy_rejecting_at_the_cap_recalls_the_nearest():
    feats = DriftingFeatures()
    bank = PolicyBank(feats, rule="calibrated", false_split_rate=0.01, calibration_samples=20, max_policies=2)
    recs = run_stream(bank, feats, [0, 0, 0, 1, 1, 1, 2])
    assert [r.decision for r in recs[-1:]] == ["recall_at_cap"] and len(bank) == 2


# ---- (c) determinism -------------------------------------------------------------------------------
def test_same_seed_same_records_and_what_if_changes_nothing():
    groups = [0, 0, 1, 0, 1, 1, 0, 2, 2, 0]

    def records(seed: int, probe: bool = False) -> list[dict]:
        feats = DriftingFeatures()
        bank = PolicyBank(feats, rule="calibrated", false_split_rate=0.05, calibration_samples=20, seed=seed)
        stream, out = Stream(), []
        for g in groups:
            obs = stream.batch(g)
            if probe:
                before = bank.calibration_rng.bit_generator.state
                bank.what_if(obs)
                assert bank.calibration_rng.bit_generator.state == before
            out.append(stable(bank.assign(obs, group_ids=g)))
            feats.step += 1
        return out

    a = records(0)
    assert a == records(0) == records(0, probe=True)
    assert [r["p_values"] for r in a] != [r["p_values"] for r in records(1)]


def test_threshold_records_are_unchanged_and_old_records_load():
    feats = DriftingFeatures()
    rec = run_stream(PolicyBank(feats), feats, [0, 0])[1]
    d = rec.to_dict()
    assert "p_values" not in d and "calibration" not in d and rec.p_values is None
    assert AssignmentRecord.from_dict(d) == rec
    cal = run_stream(PolicyBank(feats, rule="calibrated", calibration_samples=20), feats, [0, 0, 0])[2]
    back = AssignmentRecord.from_dict(json.loads(json.dumps(cal.to_dict())))
    assert back == cal and set(back.p_values) == {0}


# ---- (d) config ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "key, value",
    [
        ("rule", "adaptive"),
        ("false_split_rate", 0.0),
        ("false_split_rate", 0.5),
        ("false_split_rate", -0.1),
        ("false_split_rate", "often"),
        ("calibration_samples", 19),
        ("calibration_samples", 50.5),
    ],
)
def test_bad_config_values_name_the_field(key, value):
    with pytest.raises(ConfigError, match=f"clustering.{key}"):
        config_from_dict({"clustering": {key: value}})


def test_config_defaults_and_from_config():
    cfg = config_from_dict({})
    assert (cfg.clustering.rule, cfg.clustering.false_split_rate, cfg.clustering.calibration_samples) == (
        "threshold", 0.001, 200
    )
    assert PolicyBank.from_config(cfg).rule == "threshold"
    cfg = config_from_dict({"clustering": {"rule": "calibrated", "false_split_rate": 0.01, "calibration_samples": 30}})
    bank = PolicyBank.from_config(cfg)
    assert (bank.rule, bank.false_split_rate, bank.calibration_samples) == ("calibrated", 0.01, 30)


# ---- (e) persistence -------------------------------------------------------------------------------
def test_saved_and_loaded_calibrated_bank_decides_the_same(tmp_path):
    cfg = config_from_dict(
        {"clustering": {"rule": "calibrated", "false_split_rate": 0.05, "calibration_samples": 20}, "seed": 4}
    )
    feats = DriftingFeatures()
    bank = PolicyBank.from_config(cfg, feats)
    stream = Stream()
    for g in [0, 0, 1, 0, 1]:
        bank.assign(stream.batch(g), group_ids=g)
    save_bank(bank, tmp_path / "bank")
    loaded = load_bank(tmp_path / "bank", feats, config=cfg)
    assert [stable(r) for r in loaded.history] == [stable(r) for r in bank.history]
    for g in [1, 0, 0]:
        obs = stream.batch(g)
        assert stable(loaded.assign(obs, group_ids=g)) == stable(bank.assign(obs, group_ids=g))
    with pytest.raises(CheckpointError, match="rule"):
        load_bank(tmp_path / "bank", feats, config=config_from_dict({"seed": 4}))
    other = config_from_dict({"clustering": {"rule": "calibrated", "calibration_samples": 20}, "seed": 4})
    with pytest.raises(CheckpointError, match="false_split_rate"):
        load_bank(tmp_path / "bank", feats, config=other)


def test_bank_saved_without_rule_settings_still_loads(tmp_path):
    feats = DriftingFeatures()
    bank = PolicyBank(feats)
    run_stream(bank, feats, [0, 0, 1])
    save_bank(bank, tmp_path / "b")
    path = tmp_path / "b" / "bank.json"
    doc = json.loads(path.read_text())
    for k in ("rule", "false_split_rate", "calibration_samples"):
        del doc["state"]["settings"][k]
    del doc["state"]["calibration_rng"]
    path.write_text(json.dumps(doc))
    loaded = load_bank(tmp_path / "b", feats, config=config_from_dict({}))
    assert loaded.rule == "threshold" and len(loaded.history) == 3
    assert [stable(r) for r in loaded.history] == [stable(r) for r in bank.history]


# ---- (f) the false-split rate ----------------------------------------------------------------------
@pytest.mark.parametrize("rate", [0.02, 0.1])
def test_rejection_rate_of_same_distribution_batches_is_at_most_the_rate(rate):
    rng = np.random.default_rng(7)
    table = rng.standard_normal((128 + 8 * 400, 6)) * np.array([1.0, 1.0, 3.0, 0.2, 1.0, 1.0])

    def fn(pid: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        return table[obs["proprio"][:, 1].astype(int)]

    def batch(start: int, n: int) -> dict[str, np.ndarray]:
        proprio = np.zeros((n, 2), np.float32)
        proprio[:, 1] = np.arange(start, start + n)
        return {"image": np.zeros((n, 4, 4, 3), np.uint8), "proprio": proprio}

    bank = PolicyBank(fn, metric="euclidean", rule="calibrated", false_split_rate=rate, calibration_samples=100)
    bank.assign(batch(0, 128))
    gen = np.random.default_rng(11)
    rejected = 0
    trials = 400
    for k in range(trials):
        cal = bank.calibrated_distances(batch(128 + 8 * k, 8), gen)
        rejected += not cal.accepted[0]
    sd = math.sqrt(rate * (1 - rate) / trials)
    assert rejected / trials <= rate + 3 * sd
    assert rejected / trials >= rate / 4  # the knob does something: not a test that never rejects


# ---- (g) the exact test at the default rate with W1: false-split rate, power, null sizes --------------
SCALES = np.array([2.0, 1.0, 1.0, 0.5, 1.0, 0.3, 1.0, 1.0])


def group_vectors(rows: int, shift: float, seed: int) -> np.ndarray:
    """``rows`` vectors of one distribution: an anisotropic 8-dim Gaussian of which a fifth is moved
    by 4 along the first axis (two clusters, as tasks of one group), plus ``shift`` on every axis."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((rows, len(SCALES))) * SCALES
    x[rng.random(rows) < 0.2, 0] += 4.0
    return x + shift


class TableFeatures:
    """Features looked up, not computed: ``proprio[:, 1]`` indexes a fixed table of vectors, one
    block of rows per group (every frame is a fresh row, so a group's frames are i.i.d.)."""

    def __init__(self, blocks: list[np.ndarray]) -> None:
        self.table = np.concatenate(blocks)
        self.starts = np.cumsum([0] + [len(b) for b in blocks])
        self.used = [0] * len(blocks)

    def __call__(self, policy_id: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self.table[obs["proprio"][:, 1].astype(int)]

    def batch(self, group: int, n: int = BATCH) -> dict[str, np.ndarray]:
        start = int(self.starts[group]) + self.used[group]
        self.used[group] += n
        assert start + n <= self.starts[group + 1], "table exhausted"
        proprio = np.zeros((n, 2), np.float32)
        proprio[:, 1] = np.arange(start, start + n)
        return {"image": np.zeros((n, 4, 4, 3), np.uint8), "proprio": proprio}


def one_group_false_splits(assignments: int, seed: int) -> tuple[int, int]:
    """A one-group stream of ``assignments`` batches of 8 frames through a bank at the defaults
    (W1, false_split_rate 0.001, calibration_samples 200: 999 draws, buffer 128): (false splits
    = policies made after the first, assignments whose nearest policy rejected)."""
    feats = TableFeatures([group_vectors(BATCH * assignments, 0.0, seed)])
    bank = PolicyBank(feats, rule="calibrated", seed=seed)
    rejected = 0
    for _ in range(assignments):
        rec = bank.assign(feats.batch(0))
        if rec.distances:
            nearest = min(sorted(rec.distances), key=lambda pid: rec.distances[pid])
            test = rec.calibration["policies"][str(nearest)]
            assert test["tested"] and rec.calibration["max_draws"] == 999
            rejected += test["accepted"] is False
    assert sum(r.decision == "new" for r in bank.history) == len(bank) - 1
    return len(bank) - 1, rejected


def binomial_bound(rate: float, n: int) -> float:
    """The rate plus three binomial standard errors at ``n`` trials."""
    return rate + 3.0 * math.sqrt(rate * (1.0 - rate) / n)


def test_false_split_rate_at_the_default_rate_with_w1():
    """1,000 assignments of one group (999 of them tested; 8-frame batches): false splits at most
    the rate plus three binomial standard errors (0.001 + 0.003, i.e. at most 3)."""
    n = 1000
    splits, rejected = one_group_false_splits(n, seed=0)
    print(f"one group, {n} assignments: {splits} false splits, {rejected} rejections by the nearest policy")
    assert splits / n <= binomial_bound(0.001, n)
    assert rejected / n <= binomial_bound(0.001, n)


def split_power(shift: float, trials: int, seed: int) -> tuple[float, list[AssignmentRecord], list[float]]:
    """A bank at the defaults holding one group (16 batches: a full 128-frame buffer); each trial
    asks what it would do with a batch of a second group (the same distribution moved by ``shift``
    on every axis), then assigns one more batch of the first group. Returns the fraction of trials
    decided ``new``, the what-if records and the W1 of the first group's batches."""
    feats = TableFeatures(
        [group_vectors(BATCH * (16 + trials), 0.0, seed), group_vectors(BATCH * trials, shift, seed + 1000)]
    )
    bank = PolicyBank(feats, rule="calibrated", seed=seed)
    for _ in range(16):
        bank.assign(feats.batch(0))
    recs, same = [], []
    for _ in range(trials):
        recs.append(bank.what_if(feats.batch(1)))
        rec = bank.assign(feats.batch(0))
        assert rec.decision == "recall"
        same.append(rec.distances[0])
    return sum(r.decision == "new" for r in recs) / trials, recs, same


def w1_summary(recs: list[AssignmentRecord], same: list[float]) -> str:
    other = [r.distances[0] for r in recs]
    return (
        f"W1 second group median {np.median(other):.2f}, "
        f"first group median {np.median(same):.2f} max {max(same):.2f}"
    )


def test_power_on_two_groups_at_the_default_rate_with_w1():
    """Batches of a clearly different second group (moved 1.5 standard units on every axis; W1
    about 1.2 buffer units against at most 0.8 for batches of the first group) are split."""
    power, recs, same = split_power(1.5, trials=20, seed=0)
    print(f"two groups, shift 1.5: power {power:.2f} over {len(recs)} batches; {w1_summary(recs, same)}")
    assert power >= 0.9
    for r in recs:
        test = r.calibration["policies"]["0"]
        assert test["tested"] and test["decided_by"] == "permutation"
        if r.decision == "new":  # a rejection needs the complete test, and no draw at or above the observed
            assert test["draws"] == 999 and test["exceedances"] == 0 and r.p_values[0] == pytest.approx(0.001)
            assert r.calibration["accepted"] == []


@pytest.mark.slow  # about 1-2 min on 2 cores (`make test-slow`)
def test_false_split_rate_and_power_over_more_assignments():
    """10,000 one-group assignments (5 seeds x 2,000) at the defaults, and the power at smaller
    separations of the second group (30 batches each)."""
    n, splits, rejected = 0, 0, 0
    for seed in range(1, 6):
        s, r = one_group_false_splits(2000, seed)
        n, splits, rejected = n + 2000, splits + s, rejected + r
    print(f"one group, {n} assignments: {splits} false splits, {rejected} rejections by the nearest policy")
    assert splits / n <= binomial_bound(0.001, n)
    assert rejected / n <= binomial_bound(0.001, n)
    powers = {}
    for shift in (0.5, 0.75, 1.0, 1.5):
        powers[shift], recs, same = split_power(shift, trials=30, seed=1)
        print(f"two groups, shift {shift}: power {powers[shift]:.2f} over {len(recs)} batches;", w1_summary(recs, same))
    assert powers[1.5] >= 0.9 and powers[0.5] <= powers[1.0] <= powers[1.5]


def test_null_draws_have_the_sizes_of_o_and_b(monkeypatch):
    """Every null draw splits the pooled m + n vectors, without replacement, into m playing O and n
    playing B_i; the distance sees sets of those sizes (W1's transport problem is m x n)."""
    rng = np.random.default_rng(0)
    m, n = 8, 40
    f_o, f_b = rng.normal(size=(m, 3)) + 0.3, rng.normal(size=(n, 3))
    splits, shapes = [], []
    real_split = calibration.null_split

    def recording_split(gen, mm, nn):
        o_idx, b_idx = real_split(gen, mm, nn)
        splits.append((o_idx, b_idx))
        return o_idx, b_idx

    monkeypatch.setattr(calibration, "null_split", recording_split)
    real_cost = calibration.transport_cost

    def recording_cost(a, b, cost, max_iter):
        shapes.append((len(a), len(b), cost.shape))
        return real_cost(a, b, cost, max_iter)

    monkeypatch.setattr(calibration, "transport_cost", recording_cost)
    res = permutation_test(f_o, f_b, "wasserstein", "buffer", 0.01, 99, np.random.default_rng(1))
    assert len(splits) == res.draws >= 1 and len(shapes) == res.draws + 1  # + the observed statistic, d(O, B_i)
    for o_idx, b_idx in splits:
        assert len(o_idx) == m and len(b_idx) == n
        assert sorted(np.concatenate([o_idx, b_idx]).tolist()) == list(range(m + n))
    assert set(shapes) == {(m, n, (m, n))}

    seen = []  # the generic path (Mahalanobis) sees sets of m and n vectors
    real_dist = get_distance("mahalanobis")

    def recording_dist(a, b):
        seen.append((a.shape, b.shape))
        return real_dist(a, b)

    monkeypatch.setattr(calibration, "get_distance", lambda name: recording_dist)
    splits.clear()
    res = permutation_test(f_o, f_b, "mahalanobis", "buffer", 0.01, 99, np.random.default_rng(1))
    assert len(seen) == res.draws + 1 and set(seen) == {((m, 3), (n, 3))}
    assert len(splits) == res.draws


def test_observed_statistic_and_p_value():
    """The observed value is d(O, B_i); p = (1 + exceedances) / (1 + draws); a test rejects only
    with all draws made, and the number of draws makes the rate attainable."""
    assert max_draws(0.001, 200) == 999 and max_draws(0.02, 200) == 200 and max_draws(0.3, 20) == 20
    for rate in (0.001, 0.003, 0.01, 0.05, 0.3):
        assert 1.0 / (1 + max_draws(rate, 20)) <= rate
    rng = np.random.default_rng(2)
    f_b = rng.normal(size=(64, 4))
    f_o = rng.normal(size=(8, 4)) + 0.5
    pooled = NullDistance(np.concatenate([f_o, f_b]), 8, "wasserstein", "buffer")
    assert pooled(np.arange(72)) == pytest.approx(get_distance("wasserstein")(*normalize_pair(f_o, f_b, "buffer")))

    def run(f_o, rate, draws, seed):
        return permutation_test(f_o, f_b, "wasserstein", "buffer", rate, draws, np.random.default_rng(seed))

    same = run(rng.normal(size=(8, 4)), 0.001, 999, 0)
    assert same.accepted and same.p_value == (1 + same.exceedances) / (1 + same.draws)
    assert same.draws < 999 and (1 + same.exceedances) / 1000 > 0.001  # stopped once acceptance was settled
    far = run(rng.normal(size=(8, 4)) + 5.0, 0.001, 999, 0)
    assert not far.accepted and far.draws == 999 and far.exceedances == 0 and far.p_value == 0.001
    runs = [run(f_o, 0.01, 99, 5) for _ in range(2)]
    assert runs[0] == runs[1]  # deterministic given the generator's state


def test_policies_not_examined_are_not_recorded_as_accepted():
    """With two well-separated groups, a batch of group 0 is tested against policy 0 (nearest),
    which accepts; policy 1 is not examined: ``tested: False``, no draws, no p-value, not in
    ``accepted``. A batch of a third group is tested against both (each with all draws)."""
    feats = TableFeatures([group_vectors(400, 0.0, 0), group_vectors(400, 30.0, 1), group_vectors(400, -30.0, 2)])
    bank = PolicyBank(feats, rule="calibrated", false_split_rate=0.01, calibration_samples=50)
    for g in (0, 0, 0, 1, 1, 1):
        bank.assign(feats.batch(g))
    assert len(bank) == 2
    rec = bank.assign(feats.batch(0))
    cal = rec.calibration
    assert rec.decision == "recall" and rec.policy_id == 0
    assert cal["test"] == "pooled_permutation" and cal["max_draws"] == 99
    assert cal["policies"]["0"]["tested"] and cal["policies"]["0"]["accepted"] is True
    assert cal["policies"]["1"] == {
        "tested": False, "draws": 0, "exceedances": None, "p_value": None, "decided_by": None, "accepted": None
    }
    assert cal["accepted"] == [0] and cal["fallback"] == [] and rec.p_values[1] is None and cal["draws"]["1"] == 0
    rec = bank.what_if(feats.batch(2))
    assert rec.decision == "new" and rec.calibration["accepted"] == []
    tests = rec.calibration["policies"].values()
    assert all(t["tested"] and t["draws"] == 99 and t["accepted"] is False for t in tests)
    assert AssignmentRecord.from_dict(json.loads(json.dumps(rec.to_dict()))) == rec


def test_too_few_splits_or_frames_fall_back_to_the_threshold():
    """A one-frame query has 129 splits against a 128-frame buffer, fewer than 10 x 999: the
    threshold decides (p-value None, ``decided_by: threshold``); so it does for a 4-frame buffer."""
    feats = TableFeatures([group_vectors(400, 0.0, 0)])
    bank = PolicyBank(feats, rule="calibrated")
    for _ in range(16):
        bank.assign(feats.batch(0))
    rec = bank.what_if(feats.batch(0, n=1))
    test = rec.calibration["policies"]["0"]
    assert not test["tested"] and test["decided_by"] == "threshold" and rec.calibration["fallback"] == [0]
    assert test["accepted"] == (rec.distances[0] <= bank.threshold) and rec.p_values == {0: None}
    small = PolicyBank(feats, rule="calibrated")
    small.assign(feats.batch(0, n=4))
    rec = small.assign(feats.batch(0, n=4))
    assert rec.calibration["fallback"] == [0] and rec.calibration["policies"]["0"]["decided_by"] == "threshold"


# ---- the null's fast path equals the generic distance ------------------------------------------------
@pytest.mark.parametrize("metric", ["wasserstein", "euclidean", "mahalanobis"])
@pytest.mark.parametrize("norm", ["buffer", "none", "l2"])
def test_null_distance_matches_generic_path(metric, norm):
    rng = np.random.default_rng(0)
    f_b = rng.normal(size=(40, 5)) * 3.0 + 1.0
    null = NullDistance(f_b, 8, metric, norm)
    dist = get_distance(metric)
    for _ in range(5):
        idx = rng.permutation(40)
        want = dist(*normalize_pair(f_b[idx[:8]], f_b[idx[8:]], norm))
        assert null(idx) == pytest.approx(want, rel=1e-9, abs=1e-12)


# ---- with training encoders: the real serial loop on one toy group -----------------------------
def _one_group_run(tmp_path, rule):
    from covers_dist.runtime.driver import Trainer

    overrides = [
        "env.tasks=[reach]",
        "clustering.update_every=4",
        "ppo.minibatch_size=100",
        "runtime.serial=true",
        "runtime.num_workers=1",
        "runtime.envs_per_worker=4",
        "runtime.total_env_steps=2900",
        "runtime.log_every_s=1000",
        "runtime.checkpoint_every=1000",
        f"clustering.rule={rule}",
        f"runtime.run_dir={tmp_path / rule}",
    ]
    trainer = Trainer(load_config("configs/smoke.yaml", overrides), log=lambda _m: None)
    try:
        return trainer.run()
    finally:
        trainer.close()


@pytest.mark.slow  # two short training runs: about 1.5 min alone on 2 cores (`make test-slow`)
def test_training_encoders_split_one_group_under_the_threshold_not_under_calibrated(tmp_path, one_torch_thread):
    """29 assignments of toy reach alone while the policy's encoder trains (seed 0): the fixed d_eps
    creates a second policy (W1 1.41 at assignment 28, against 0.45-0.68 before), the calibrated
    test compares that draw with the buffer's own spread in the same drifted features and recalls."""
    threshold = _one_group_run(tmp_path, "threshold")
    calibrated = _one_group_run(tmp_path, "calibrated")
    assert threshold["num_policies"] == 2, threshold["policy_counts"]
    assert calibrated["num_policies"] == 1, calibrated["policy_counts"]
    assert calibrated["ari"] == 1.0


# ---- (h) the tail of the own policy's tests (covers-dist report) -----------------------------------------
def tail_record(index, decision, policy_id, tests, group, distances=None):
    """A calibrated record at rate 0.01 (N = 99 draws: one exceedance settles acceptance)."""
    policies = {
        str(pid): {"tested": t is not None and t[0] == "perm", "draws": t[1] if t else 0,
                   "exceedances": t[2] if t else None, "p_value": None,
                   "decided_by": "permutation" if t and t[0] == "perm" else "threshold", "accepted": None}
        for pid, t in tests.items()
    }
    return AssignmentRecord(
        index=index, policy_id=policy_id, decision=decision, new=decision in ("adopt", "new"),
        distances=distances or {pid: 1.0 for pid in tests}, threshold=1.0, metric="wasserstein",
        mode="distance", num_observations=8, episode_indices=list(range(8 * index, 8 * index + 8)),
        wall_time_ms=0.0, time_unix=0.0, true_groups=None if group is None else [group] * 8,
        calibration={"false_split_rate": 0.01, "max_draws": 99, "policies": policies},
        p_values={pid: None for pid in tests},
    )


def tail_records(labelled=True):
    g = (lambda x: x) if labelled else (lambda x: None)
    return [
        tail_record(0, "adopt", 0, {}, g(0)),
        tail_record(1, "recall", 0, {0: ("perm", 5, 1)}, g(0)),  # first exceedance at draw 5
        tail_record(2, "new", 1, {0: ("perm", 99, 0)}, g(1)),  # group 1's first batch: a true new group
        tail_record(3, "recall", 1, {1: ("perm", 50, 1), 0: None}, g(1)),
        # group 0 again, every policy rejects: a false split, its nearest policy's test (no exceedance in 99)
        tail_record(4, "new", 2, {0: ("perm", 99, 0), 1: ("perm", 99, 0)}, g(0), distances={0: 1.2, 1: 3.0}),
        tail_record(5, "recall", 0, {0: ("threshold", 0, None)}, g(0)),  # decided by the threshold: left out
        tail_record(6, "recall", 2, {2: ("perm", 1, 1)}, g(0)),
    ]


def test_calibration_tail_counts_the_own_policys_tests():
    from covers_dist.clustering import calibration_tail
    from covers_dist.evaluation.report import calibration_tail_section

    tail = calibration_tail(tail_records())
    # own tests: first exceedance at 5, 50, none in 99 (-> 100), 1
    assert (tail["tests"], tail["skipped"], tail["false_splits"], tail["labelled"]) == (4, 1, 1, True)
    assert (tail["max_draws"], tail["false_split_rate"]) == (99, 0.01)
    assert tail["rows"] == [{"k": 10, "count": 2, "expected": 0.4}, {"k": 100, "count": 1, "expected": 0.04}]
    text = "\n".join(calibration_tail_section(tail))
    assert "N = 99 draws" in text and "| 100 | 1 | 0.04 | 25.00 |" in text and "1 false split(s)" in text

    # without true group ids the new decisions cannot be told apart: only recalls count
    tail = calibration_tail(tail_records(labelled=False))
    assert (tail["tests"], tail["skipped"], tail["false_splits"], tail["labelled"]) == (3, 1, None, False)
    assert [r["count"] for r in tail["rows"]] == [1, 0]
    assert "false splits unknown" in "\n".join(calibration_tail_section(tail))

    # a new decision with no distances in its record: counted as a split, its test left out
    bare = tail_records()[:2] + [tail_record(2, "new", 1, {}, 0, distances={})]
    tail = calibration_tail(bare)
    assert (tail["tests"], tail["skipped"], tail["false_splits"]) == (1, 1, 1)
    assert "| 10 | 0 | 0.10 | 0.00 |" in "\n".join(calibration_tail_section(tail))

    # threshold records (no calibration): no tail, no section
    thr = [AssignmentRecord.from_dict({**r.to_dict(), "calibration": None, "p_values": None}) for r in tail_records()]
    assert calibration_tail(thr) is None and calibration_tail_section(None) == []


def test_calibration_tail_of_a_real_bank_matches_its_records():
    """Three groups at rate 0.01: the tail reads every recall's test of the recalled policy."""
    from covers_dist.clustering import calibration_tail

    feats = DriftingFeatures()
    order = [int(g) for g in np.random.default_rng(3).permutation([0, 1, 2] * 12)]
    bank = PolicyBank(feats, metric="wasserstein", rule="calibrated", false_split_rate=0.01, calibration_samples=50, seed=1)
    recs = run_stream(bank, feats, order)
    tail = calibration_tail(recs)
    own = [r.calibration["policies"][str(r.policy_id)] for r in recs if r.decision == "recall"]
    tested = [t for t in own if t["tested"]]
    assert tail["false_splits"] == len(bank) - 3 == 0
    assert tail["tests"] == len(tested) and tail["skipped"] == len(own) - len(tested)
    assert tail["rows"][0] == {"k": 10, "count": sum(t["draws"] >= 10 for t in tested), "expected": len(tested) / 10}
    assert [r["k"] for r in tail["rows"]] == [10, 100]  # N = max(50, 99) = 99
