"""A bank that heals: a false split is merged back, and near-equal candidates prefer the trained
policy (synthetic features carried in the proprio vector)."""

from __future__ import annotations

import numpy as np
import pytest

from covers_dist.clustering import PolicyBank, SharedFeatures, load_bank, save_bank
from covers_dist.clustering.bank import MIN_MERGE_FRAMES
from covers_dist.config import ConfigError, load_config


def _obs(x: np.ndarray) -> dict[str, np.ndarray]:
    n = len(x)
    image = (np.arange(n)[:, None, None, None] % 256 * np.ones((1, 4, 4, 3))).astype(np.uint8)
    return {"image": image, "proprio": x.astype(np.float32)}


def _batch(rng: np.random.Generator, centre: float, n: int = 8, spread: float = 1.0) -> dict[str, np.ndarray]:
    return _obs(rng.normal(scale=spread, size=(n, 4)) + centre)


def _bank(**kw) -> PolicyBank:
    kw.setdefault("threshold", 1.0)
    kw.setdefault("buffer_size", 64)
    kw.setdefault("merge_threshold", 1.0)
    kw.setdefault("merge_every", 1)
    return PolicyBank(SharedFeatures(lambda obs: obs["proprio"]), seed=3, **kw)


def _false_split(bank: PolicyBank, rng: np.random.Generator) -> None:
    """Policy 0 learns group A (centre 0); policy 1 is forced on more frames of group A (a false
    split: its buffer is group A's distribution); policy 2 holds group B (centre 40)."""
    for _ in range(4):
        bank.assign(_batch(rng, 0.0), group_ids=0)
    assert bank.policy_ids == [0]
    bank.threshold = 1e-9  # every batch is "far": the rule creates policies
    bank.merge_threshold, saved = None, bank.merge_threshold
    bank.assign(_batch(rng, 0.0), group_ids=0)  # policy 1: group A again
    bank.assign(_batch(rng, 40.0), group_ids=1)  # policy 2: group B
    bank.threshold, bank.merge_threshold = 1.0, saved
    assert bank.policy_ids == [0, 1, 2]


def test_a_false_split_is_merged_into_the_older_policy_and_never_chosen_again():
    rng = np.random.default_rng(0)
    bank = _bank()
    _false_split(bank, rng)
    # policy 1 holds fewer than MIN_MERGE_FRAMES frames: not judged yet
    assert len(bank.entries[1].buffer) < MIN_MERGE_FRAMES
    bank.entries[1].buffer.add(_batch(rng, 0.0, n=MIN_MERGE_FRAMES))  # more of its episodes' first frames
    record = bank.assign(_batch(rng, 40.0), group_ids=1)
    assert record.merges and record.merges[0]["retired"] == 1 and record.merges[0]["into"] == 0
    assert record.merges[0]["distance"] <= bank.merge_threshold
    assert bank.policy_ids == [0, 2] and list(bank.retired) == [1]
    assert record.policy_id == 2 and record.decision == "recall"
    # the retired policy's episodes and labels are the absorbing policy's now: the ARI is whole again
    assert bank.episode_policy[4] == 0 and bank.labels[4] == (0, 0)
    assert bank.metrics()["ari"] == pytest.approx(1.0)
    summary = bank.summary()
    assert summary["num_policies"] == 2 and summary["policies_created"] == 3
    assert summary["retired"][0]["policy_id"] == 1 and summary["retired"][0]["merged_into"] == 0
    # never chosen again, and its id is never reused
    for _ in range(3):
        assert bank.assign(_batch(rng, 0.0), group_ids=0).policy_id == 0
    bank.threshold = 1e-9
    assert bank.assign(_batch(rng, -40.0), group_ids=2).policy_id == 3


def test_distinct_groups_are_never_merged():
    rng = np.random.default_rng(1)
    bank = _bank()
    for centre, g in ((0.0, 0), (40.0, 1), (-40.0, 2)) * 4:
        bank.assign(_batch(rng, centre), group_ids=g)
    assert bank.policy_ids == [0, 1, 2] and not bank.merges and not bank.retired


def test_merges_survive_a_save_and_load(tmp_path):
    rng = np.random.default_rng(2)
    bank = _bank()
    _false_split(bank, rng)
    bank.entries[1].buffer.add(_batch(rng, 0.0, n=MIN_MERGE_FRAMES))
    bank.assign(_batch(rng, 0.0), group_ids=0)
    assert list(bank.retired) == [1]
    save_bank(bank, tmp_path / "b")
    again = load_bank(tmp_path / "b", feature_fn=bank.feature_fn)
    assert again.policy_ids == [0, 2] and list(again.retired) == [1]
    assert again.merges == bank.merges and again.merge_threshold == 1.0 and again.merge_every == 1
    assert again.summary()["retired"] == bank.summary()["retired"]
    assert again.next_policy_id() == 3
    batch = _batch(rng, 0.0)
    assert again.assign(batch, group_ids=0).to_dict()["distances"] == bank.assign(batch, group_ids=0).to_dict()["distances"]


def test_healing_is_off_without_a_merge_threshold_and_checks_its_settings():
    rng = np.random.default_rng(3)
    bank = _bank(merge_threshold=None)
    _false_split(bank, rng)
    bank.entries[1].buffer.add(_batch(rng, 0.0, n=MIN_MERGE_FRAMES))
    for _ in range(3):
        bank.assign(_batch(rng, 40.0), group_ids=1)
    assert bank.policy_ids == [0, 1, 2] and not bank.merges
    with pytest.raises(ValueError, match="merge_threshold"):
        _bank(merge_threshold=0.0)
    with pytest.raises(ValueError, match="merge_every"):
        _bank(merge_every=0)
    with pytest.raises(ValueError, match="tie_margin"):
        _bank(tie_margin=1.0)
    with pytest.raises(ValueError, match="cannot merge policy 1 into 1"):
        bank.merge(1, 1)
    with pytest.raises(ConfigError, match="merge_threshold"):
        load_config("smoke", ["clustering.merge_threshold=-1"])
    with pytest.raises(ConfigError, match="tie_margin"):
        load_config("smoke", ["clustering.tie_margin=0.95"])


@pytest.mark.parametrize("rule", ["threshold", "calibrated"])
def test_near_equal_candidates_prefer_the_policy_that_has_trained(rule):
    """Two policies hold one group (a false split kept); a batch as near to both is recalled to
    the one assigned more often when the margin allows, to the nearest without it."""

    def bank_with(margin: float) -> PolicyBank:
        rng = np.random.default_rng(4)
        bank = _bank(merge_threshold=None, tie_margin=margin, threshold=3.0, false_split_rate=0.01)
        for _ in range(6):
            bank.assign(_batch(rng, 0.0, n=8), group_ids=0)
        bank.threshold = 1e-9
        bank.assign(_batch(rng, 0.3, n=8), group_ids=0)  # policy 1: a near copy, assigned once
        bank.entries[1].buffer.add(_batch(rng, 0.3, n=8))  # enough frames for a permutation test
        bank.threshold, bank.rule = 3.0, rule
        assert bank.policy_ids == [0, 1]
        return bank

    probe = _batch(np.random.default_rng(9), 0.3, n=8)
    plain = bank_with(0.0)
    d = plain.what_if(probe).distances
    nearest = min(d, key=d.get)
    assert plain.what_if(probe).policy_id == nearest
    margin = min(0.9, 1.0 - min(d.values()) / max(d.values()) + 0.05)  # wide enough to hold both
    wide = bank_with(margin)
    assert wide.entries[0].assignments > wide.entries[1].assignments
    assert wide.what_if(probe).policy_id == 0


def test_the_clustering_service_keeps_a_merge_across_a_snapshot_and_skips_the_retired_policy():
    """In the service a run talks to: episodes that finish on a policy merged meanwhile are
    recorded without error, queries never choose it, and a snapshot restores the merge."""
    from api_helpers import STREAM, api_config, filled_service, initial_obs

    from covers_dist.runtime.clustering_service import ClusteringService

    cfg = api_config()
    service = filled_service(cfg, STREAM)
    young = max(service.bank.policy_ids)
    service.bank.merge(young, 0, distance=0.1)
    summaries = [{"episode_index": 10_000 + i, "policy_id": young, "assigned_policy": young, "success": 1.0,
                  "return": 1.0} for i in range(2)]  # fmt: skip
    service.record_episodes(summaries)  # the retired policy's last episodes: nothing to record, no error
    obs = initial_obs(cfg, "reach", "e", [500, 501, 502, 503])
    assert service.what_if(obs)["policy_id"] != young
    again = ClusteringService(cfg)
    again.restore(service.snapshot())
    assert list(again.bank.retired) == [young] and again.bank.merges == service.bank.merges
    assert again.summary()["policies_created"] == service.summary()["policies_created"] == len(service.bank) + 1
