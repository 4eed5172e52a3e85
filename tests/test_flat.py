"""Flat over a long run: the bank's metrics come from a contingency table kept as episodes are
labelled (the same figures as recounting every episode), the HTTP snapshot shares the history
instead of copying it, a checkpoint copies only the logs that changed, and the soak benchmark
measures it all."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from covers_dist.api.snapshot import HistoryView
from covers_dist.clustering.metrics import adjusted_rand_index, confusion_table, policy_counts, table_metrics
from covers_dist.clustering.persistence import load_bank, save_bank

from test_clustering_heal import _bank, _batch, _false_split


def recount(bank) -> dict:
    """The metrics recounted over every labelled episode (what the bank computed before)."""
    policies, groups = bank.label_pairs()
    return {
        "ari": adjusted_rand_index(policies, groups),
        "episodes_labelled": len(policies),
        "policy_counts": {str(k): v for k, v in policy_counts(policies).items()},
        "confusion": confusion_table(policies, groups),
    }


@pytest.mark.parametrize("seed", range(5))
def test_the_table_gives_the_figures_of_a_recount(seed):
    rng = np.random.default_rng(seed)
    counts: dict = {}
    policies = rng.integers(0, 4, size=200).tolist()
    groups = rng.integers(0, 3, size=200).tolist()
    for p, g in zip(policies, groups):
        counts[(p, g)] = counts.get((p, g), 0) + 1
    got = table_metrics(counts)
    assert got["ari"] == pytest.approx(adjusted_rand_index(policies, groups), abs=1e-12)
    assert got["confusion"] == confusion_table(policies, groups)
    assert got["policy_counts"] == {str(k): v for k, v in policy_counts(policies).items()}
    assert table_metrics({})["ari"] is None and table_metrics({})["episodes_labelled"] == 0


def test_the_banks_table_follows_assignments_merges_and_a_reload(tmp_path):
    rng = np.random.default_rng(0)
    bank = _bank()
    _false_split(bank, rng)
    assert bank.metrics() == recount(bank)
    bank.entries[1].buffer.add(_batch(rng, 0.0, n=16))
    record = bank.assign(_batch(rng, 40.0), group_ids=1)  # heals: policy 1 merged into 0
    assert record.merges and bank.metrics() == recount(bank)
    bank.record_episode_stats(0, 1.0, 2.0, episode_index=10_000, group_id=0)  # an episode labelled by its report
    assert bank.metrics() == recount(bank)
    save_bank(bank, tmp_path / "bank")
    loaded = load_bank(tmp_path / "bank")
    assert loaded.metrics() == recount(loaded) == bank.metrics()


def test_the_snapshots_history_is_a_view_of_the_first_n_records():
    items = [{"index": i} for i in range(10)]
    view = HistoryView(items, 7)
    assert len(view) == 7 and view[0] == {"index": 0} and view[-1] == {"index": 6}
    assert view[5:100] == [{"index": 5}, {"index": 6}] and view[:] == items[:7]
    items.append({"index": 10})  # the cache's list grows; the view still ends where it did
    assert len(view) == 7 and view[6:] == [{"index": 6}]
    with pytest.raises(IndexError):
        view[7]


def test_a_checkpoint_copies_only_the_logs_that_changed(tiny_serial_run, tmp_path):
    import shutil

    from covers_dist.runtime.checkpoint import latest_valid_checkpoint
    from covers_dist.runtime.run_storage import push_checkpoint

    from test_runtime_serial import tiny_cfg

    run_dir = tmp_path / "run"
    shutil.copytree(tiny_serial_run[2], run_dir)
    (run_dir / "metrics.jsonl.1.gz").write_bytes(b"a closed segment")
    store = tmp_path / "store"
    cfg = tiny_cfg(run_dir, f"runtime.storage={store}")
    ckpt = latest_valid_checkpoint(run_dir, log=lambda *_: None)
    push_checkpoint(cfg, ckpt)
    first = {p.name: p.stat().st_mtime_ns for p in store.iterdir() if p.is_file()}
    assert {"metrics.jsonl", "metrics.jsonl.1.gz", "episodes.jsonl"} <= set(first)
    with open(run_dir / "metrics.jsonl", "a") as fh:  # the live log grows
        fh.write(json.dumps({"iteration": 99}) + "\n")
    os.utime(run_dir / "metrics.jsonl")
    push_checkpoint(cfg, ckpt)
    second = {p.name: p.stat().st_mtime_ns for p in store.iterdir() if p.is_file()}
    assert second["metrics.jsonl.1.gz"] == first["metrics.jsonl.1.gz"]  # copied once
    assert second["metrics.jsonl"] != first["metrics.jsonl"]
    assert (store / "metrics.jsonl").read_bytes() == (run_dir / "metrics.jsonl").read_bytes()


def test_the_soak_benchmark_reports_start_end_and_slopes(tmp_path):
    from covers_dist.bench.soak import slope_per_1000, soak

    assert slope_per_1000([1.0, 2.0, 3.0]) == pytest.approx(1000.0)
    report = soak(30, 5, 10, 0, [], tmp_path / "run", log=lambda *_: None)
    assert report["iterations"] == 30 and report["policies"] >= 1
    for name in ("iteration_s", "snapshot_ms", "rss_mib", "assign_ms", "record_ms"):
        s = report["series"][name]
        assert s["start"] > 0 and s["end"] > 0 and np.isfinite(s["slope_per_1000"]), (name, s)


def _service_with_history(cfg, storage, batches):
    """A clustering service on ``storage`` after ``batches`` assignments of toy episodes."""
    from api_helpers import initial_obs, policy_weights

    from covers_dist.runtime.clustering_service import ClusteringService

    service = ClusteringService(cfg, storage=str(storage))
    weights = {0: (1, policy_weights(cfg, 0))}
    for it in range(batches):
        task, g = [("reach", "e"), ("push", "r")][it % 2]
        idx = [2 * it, 2 * it + 1]
        record = service.assign(it, initial_obs(cfg, task, g, idx), idx, [list(cfg.env.tasks).index(task)] * 2, weights)
        pid = int(record["policy_id"])
        if pid not in weights:
            weights[pid] = (1, policy_weights(cfg, pid))
            service.sync_weights({pid: weights[pid]})
        service.record_episodes([{"episode_index": i, "policy_id": pid, "success": 1.0, "return": 1.0} for i in idx])
    return service


def test_the_live_state_journals_its_history_and_a_restart_reads_it_all_back(tmp_path, monkeypatch):
    """The live state holds only the records after the last sealed journal chunk (what a persist
    writes stays the same size as the history grows); a restarted service reads the chunks and the
    state back into the same history; a restore from a (whole) checkpoint bank starts the journal over."""
    import io
    import tarfile

    from api_helpers import smoke_config

    from covers_dist.runtime import clustering_service as cs

    monkeypatch.setattr(cs, "HISTORY_CHUNK", 4)
    cfg = smoke_config("clustering.initial_frames=1", "env.image_size=16", "network.channels=[2,4]", "network.hidden=8")
    store = tmp_path / "store"
    service = _service_with_history(cfg, store, 11)
    chunks = sorted(p.name for p in (store / "clustering_live" / "history").iterdir())
    assert chunks == ["000000.json", "000001.json"]

    def live_records():
        with tarfile.open(fileobj=io.BytesIO((store / cs.LIVE_STATE).read_bytes())) as tar:
            doc = json.load(tar.extractfile("bank.json"))
        return doc["state"].get("history_offset", 0), len(doc["state"]["history"])

    assert live_records() == (8, 3)
    restarted = cs.ClusteringService(cfg, storage=str(store))
    assert [r.to_dict() for r in restarted.bank.history] == [r.to_dict() for r in service.bank.history]
    assert restarted.metrics()["ari"] == service.metrics()["ari"] and restarted.recorded_through == 21
    whole = service.snapshot()  # what a checkpoint holds: the whole history
    restarted.restore(whole)
    assert live_records() == (0, 11)
    again = cs.ClusteringService(cfg, storage=str(store))
    assert len(again.bank.history) == 11
