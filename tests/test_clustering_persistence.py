"""Saving and restoring the policy bank: exact round trips, clear errors, atomic replacement."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from covers_dist.clustering import CheckpointError, PolicyBank, SharedFeatures, load_bank, save_bank
from covers_dist.clustering.persistence import STATE_FILE
from covers_dist.config import load_config

FEATURES = SharedFeatures(lambda obs: obs["proprio"])


def _obs(rng: np.random.Generator, centre: float, n: int = 4) -> dict[str, np.ndarray]:
    return {
        "image": rng.integers(0, 256, size=(n, 8, 8, 3), dtype=np.uint8),
        "proprio": (rng.normal(scale=0.3, size=(n, 5)) + centre).astype(np.float32),
    }


def _filled_bank(rng: np.random.Generator, **kw) -> PolicyBank:
    bank = PolicyBank(FEATURES, threshold=2.0, buffer_size=6, **kw)
    for g in (0, 1, 0, 2, 1, 0):
        bank.assign(_obs(rng, 10.0 * g), group_ids=g)
    bank.record_episode_stats(1, success=1.0, ret=-2.0, group_id=1, episode_index=100)
    return bank


CLOCK_FIELDS = ("wall_time_ms", "time_unix", "created_at_time")


def _state(bank: PolicyBank, clocks: bool = True) -> str:
    s = bank.summary()
    s["history"] = [r.to_dict() for r in bank.history]
    s["labels"] = sorted(bank.labels.items())
    s["rng"] = [bank.entries[p].buffer.state() for p in bank.policy_ids]
    if not clocks:  # two banks that continue in step differ only in when they did it
        for row in s["history"] + s["policies"]:
            for k in CLOCK_FIELDS:
                row.pop(k, None)
    return json.dumps(s, sort_keys=True)


@pytest.mark.parametrize("replacement", ["reservoir", "fifo"])
def test_round_trip_is_exact_and_continues_identically(tmp_path, replacement):
    rng = np.random.default_rng(0)
    bank = _filled_bank(rng, replacement=replacement)
    save_bank(bank, tmp_path / "bank")
    restored = load_bank(tmp_path / "bank", FEATURES)
    assert _state(restored) == _state(bank)
    for pid in bank.policy_ids:
        a, b = bank.entries[pid].buffer.observations(), restored.entries[pid].buffer.observations()
        for k in ("image", "proprio"):
            assert a[k].dtype == b[k].dtype
            np.testing.assert_array_equal(a[k], b[k])
    # both continue the same way (buffer RNGs included)
    for g in (2, 0, 1, 1):
        obs = _obs(rng, 10.0 * g, n=8)
        r1, r2 = bank.assign(obs, group_ids=g), restored.assign(obs, group_ids=g)
        assert (r1.policy_id, r1.decision, r1.distances) == (r2.policy_id, r2.decision, r2.distances)
    assert _state(restored, clocks=False) == _state(bank, clocks=False)
    for pid in bank.policy_ids:
        np.testing.assert_array_equal(
            bank.entries[pid].buffer.observations()["proprio"], restored.entries[pid].buffer.observations()["proprio"]
        )


def test_ground_truth_bank_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    bank = _filled_bank(rng, mode="ground_truth")
    save_bank(bank, tmp_path)
    restored = load_bank(tmp_path)
    assert restored.group_policy == bank.group_policy and _state(restored) == _state(bank)


def test_saving_again_replaces_and_cleans_up(tmp_path):
    rng = np.random.default_rng(2)
    bank = _filled_bank(rng)
    save_bank(bank, tmp_path)
    bank.assign(_obs(rng, 30.0), group_ids=3)
    save_bank(bank, tmp_path)
    assert len([p for p in tmp_path.iterdir() if p.suffix == ".npz"]) == 1
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert len(load_bank(tmp_path)) == 4


def test_failed_save_leaves_previous_checkpoint_usable(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    bank = _filled_bank(rng)
    save_bank(bank, tmp_path)
    before = _state(load_bank(tmp_path))
    bank.assign(_obs(rng, 30.0), group_ids=3)
    real_replace = os.replace

    def crash_on_commit(src, dst):  # the process dies just before bank.json is renamed into place
        if str(dst).endswith(STATE_FILE):
            raise OSError("disk full")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", crash_on_commit)
    with pytest.raises(OSError, match="disk full"):
        save_bank(bank, tmp_path)
    monkeypatch.setattr(os, "replace", real_replace)
    assert _state(load_bank(tmp_path)) == before
    assert len([p for p in tmp_path.iterdir() if p.suffix == ".npz"]) == 1


def test_missing_and_corrupt_files_raise_clear_errors(tmp_path):
    assert issubclass(CheckpointError, ValueError)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_bank(tmp_path / "nowhere")
    with pytest.raises(CheckpointError, match="bank.json is missing"):
        load_bank(tmp_path)
    rng = np.random.default_rng(4)
    save_bank(_filled_bank(rng), tmp_path)
    state = tmp_path / STATE_FILE
    good = state.read_text()
    (npz,) = [p for p in tmp_path.iterdir() if p.suffix == ".npz"]

    state.write_text(good[: len(good) // 2])
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_bank(tmp_path)
    doc = json.loads(good)
    for key, value, match in [
        ("format_version", 99, "format version 99 is not supported"),
        ("format", "something-else", "not a policy-bank checkpoint"),
    ]:
        state.write_text(json.dumps({**doc, key: value}))
        with pytest.raises(CheckpointError, match=match):
            load_bank(tmp_path)
    broken = json.loads(good)
    broken["state"]["entries"][0]["buffer"]["size"] = 5
    state.write_text(json.dumps(broken))
    with pytest.raises(CheckpointError, match="policy 0"):
        load_bank(tmp_path)
    broken = json.loads(good)
    del broken["state"]["history"]
    state.write_text(json.dumps(broken))
    with pytest.raises(CheckpointError, match="inconsistent bank state"):
        load_bank(tmp_path)

    state.write_text(good)
    blob = bytearray(npz.read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    npz.write_bytes(bytes(blob))
    with pytest.raises(CheckpointError, match="SHA-256 does not match"):
        load_bank(tmp_path)
    npz.unlink()
    with pytest.raises(CheckpointError, match="is missing"):
        load_bank(tmp_path)


def test_config_mismatch_is_named(tmp_path):
    cfg = load_config(overrides=["clustering.buffer_size=6", "clustering.threshold=2.0", "clustering.feature_norm=buffer"])
    rng = np.random.default_rng(5)
    bank = _filled_bank(rng)
    save_bank(bank, tmp_path)
    assert len(load_bank(tmp_path, config=cfg)) == len(bank)
    other = load_config(overrides=["clustering.buffer_size=6", "clustering.metric=euclidean", "clustering.feature_norm=buffer"])
    with pytest.raises(CheckpointError, match="metric: saved 'wasserstein', config 'euclidean'; threshold"):
        load_bank(tmp_path, config=other)
