"""Bounded run logs: JSONL rotation into gzip segments, the shared reader, resume truncation,
TensorBoard event-file rotation and purge, and the config keys. No Ray."""

import gzip
import json
import time
from pathlib import Path

import pytest

from covers_dist.config import ConfigError, RuntimeConfig, load_config
from covers_dist.runtime.logfiles import (
    JsonlLog,
    read_jsonl_file,
    read_jsonl_segments,
    remove_log,
    segment_paths,
    truncate_after_iteration,
)
from covers_dist.runtime.metrics import MetricsWriter


def _row(i, pad=0):
    return {"iteration": i, "x": "a" * pad}


def _size(row):
    return len(json.dumps(row)) + 1


def _names(run, name):
    return [p.name for p in segment_paths(run, name)]


def test_rotates_at_the_limit_into_a_gzip_segment(tmp_path):
    row = _row(0, pad=40)
    limit = 3 * _size(row)  # the third row reaches the limit
    log = JsonlLog(tmp_path / "m.jsonl", rotate_bytes=limit, keep=5)
    log.write([_row(1, 40), _row(2, 40)])
    assert (tmp_path / "m.jsonl").stat().st_size == 2 * _size(row)
    assert _names(tmp_path, "m.jsonl") == []
    log.write([_row(3, 40)])
    assert _names(tmp_path, "m.jsonl") == ["m.jsonl.1.gz"]
    assert (tmp_path / "m.jsonl").stat().st_size == 0
    with gzip.open(tmp_path / "m.jsonl.1.gz", "rt") as fh:
        assert [json.loads(line)["iteration"] for line in fh] == [1, 2, 3]
    log.write([_row(4, 40)])
    log.close()
    assert [r["iteration"] for r in read_jsonl_segments(tmp_path, "m.jsonl")] == [1, 2, 3, 4]


def test_keeps_the_newest_segments_and_reads_them_in_order(tmp_path):
    limit = 2 * _size(_row(10, 40))  # two rows per segment (iterations 10..99 have the same size)
    log = JsonlLog(tmp_path / "e.jsonl", rotate_bytes=limit, keep=3)
    for i in range(10, 31):  # 21 rows: 10 segments of two, one row live
        log.write([_row(i, 40)])
    log.close()
    assert _names(tmp_path, "e.jsonl") == ["e.jsonl.8.gz", "e.jsonl.9.gz", "e.jsonl.10.gz"]
    assert [r["iteration"] for r in read_jsonl_segments(tmp_path, "e.jsonl")] == list(range(24, 31))
    # a new writer continues the numbering and the pruning
    log = JsonlLog(tmp_path / "e.jsonl", rotate_bytes=limit, keep=3)
    log.write([_row(31, 40)])
    log.close()
    assert _names(tmp_path, "e.jsonl") == ["e.jsonl.9.gz", "e.jsonl.10.gz", "e.jsonl.11.gz"]
    assert [r["iteration"] for r in read_jsonl_segments(tmp_path, "e.jsonl")] == list(range(26, 32))


def test_remove_log_deletes_every_segment(tmp_path):
    log = JsonlLog(tmp_path / "e.jsonl", rotate_bytes=100, keep=5)
    log.write([_row(i, 100) for i in range(4)])
    log.close()
    (tmp_path / "other.jsonl").write_text("{}\n")
    assert len(segment_paths(tmp_path, "e.jsonl")) == 4
    remove_log(tmp_path, "e.jsonl")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.jsonl"]


def test_no_rotation_without_a_limit(tmp_path):
    log = JsonlLog(tmp_path / "e.jsonl", rotate_bytes=None, keep=0)
    log.write([_row(i, 200) for i in range(100)])
    log.close()
    assert _names(tmp_path, "e.jsonl") == []
    assert len(list(read_jsonl_segments(tmp_path, "e.jsonl"))) == 100


def test_an_interrupted_rotation_and_an_unfinished_line_are_repaired(tmp_path):
    # killed after the live file became segment 1 but before it was compressed, and mid-append
    (tmp_path / "e.jsonl.1").write_text("".join(json.dumps(_row(i)) + "\n" for i in (1, 2)))
    (tmp_path / "e.jsonl").write_text(json.dumps(_row(3)) + "\n" + '{"iteration": 4, "x"')
    assert [r["iteration"] for r in read_jsonl_segments(tmp_path, "e.jsonl")] == [1, 2, 3]
    log = JsonlLog(tmp_path / "e.jsonl", rotate_bytes=10_000, keep=5)
    log.write([_row(4)])
    log.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.jsonl", "e.jsonl.1.gz"]
    assert [r["iteration"] for r in read_jsonl_segments(tmp_path, "e.jsonl")] == [1, 2, 3, 4]


def test_the_reader_names_a_bad_line(tmp_path):
    (tmp_path / "e.jsonl").write_text('{"iteration": 1}\nnot json\n{"iteration": 2}\n')
    with pytest.raises(ValueError, match=r"e\.jsonl:2 is not valid JSON"):
        list(read_jsonl_segments(tmp_path, "e.jsonl"))
    assert [r["iteration"] for r in read_jsonl_segments(tmp_path, "e.jsonl", strict=False)] == [1, 2]
    assert list(read_jsonl_segments(tmp_path, "missing.jsonl")) == []


def _episode(i, iteration):
    return {"episode_index": i, "task": "reach" if i % 2 else "push", "g": "e", "group_id": i % 2, "policy_id": 0,
            "return": float(i), "success": float(i % 3 == 0), "length": 25, "assigned_policy": 0,
            "env_steps": 25 * (i + 1), "iteration": iteration}


def _metrics_row(iteration):
    return {"iteration": iteration, "env_steps": 100 * iteration, "num_policies": 1, "ari": 1.0, "loss": 0.5}


def _write_run(run, iterations, writer):
    for it in iterations:
        writer.episodes([_episode(4 * (it - 1) + k, it) for k in range(4)])
        writer.scalars(_metrics_row(it))


def test_metrics_writer_rotates_and_every_reader_sees_all_kept_rows(tmp_path):
    from covers_dist.runtime.evaluation import _episode_rows
    from covers_dist.commands.plot import _read_jsonl, make_plots

    writer = MetricsWriter(tmp_path, tensorboard=False, rotate_mb=1_000 / 2**20, keep=100)
    _write_run(tmp_path, range(1, 21), writer)
    writer.close()
    assert len(segment_paths(tmp_path, "episodes.jsonl")) >= 5
    assert len(segment_paths(tmp_path, "metrics.jsonl")) >= 1
    assert [e["episode_index"] for e in _read_jsonl(tmp_path, "episodes.jsonl")] == list(range(80))
    assert [m["iteration"] for m in _read_jsonl(tmp_path, "metrics.jsonl")] == list(range(1, 21))
    assert [e["episode_index"] for e in _episode_rows(tmp_path, 50)] == list(range(50))
    # plot reads the rotated logs: the live episodes file alone is not enough
    (tmp_path / "episodes.jsonl").write_text("")
    names = {"success_return.png", "policy_timeline.png", "ari_policies.png", "ppo_updates.png"}
    assert {p.name for p in make_plots(tmp_path)} == names


def test_resume_truncation_removes_exactly_the_later_rows(tmp_path):
    writer = MetricsWriter(tmp_path, tensorboard=False, rotate_mb=1_500 / 2**20, keep=100)
    _write_run(tmp_path, range(1, 11), writer)
    writer.close()
    (tmp_path / "eval.jsonl").write_text("".join(json.dumps({"iteration": i, "pairs": []}) + "\n" for i in (3, 6, 9)))
    episodes_before = list(read_jsonl_segments(tmp_path, "episodes.jsonl"))
    newest = segment_paths(tmp_path, "episodes.jsonl")[-1]
    assert any(e["iteration"] > 6 for e in read_jsonl_file(newest, live=False))  # a segment is rewritten too

    writer = MetricsWriter(tmp_path, tensorboard=False, resume_iteration=6, rotate_mb=1_500 / 2**20, keep=100)
    assert [m["iteration"] for m in read_jsonl_segments(tmp_path, "metrics.jsonl")] == list(range(1, 7))
    assert list(read_jsonl_segments(tmp_path, "episodes.jsonl")) == [e for e in episodes_before if e["iteration"] <= 6]
    assert [ev["iteration"] for ev in read_jsonl_segments(tmp_path, "eval.jsonl")] == [3, 6]
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    # the redone iterations are logged once
    _write_run(tmp_path, range(7, 11), writer)
    writer.close()
    assert [m["iteration"] for m in read_jsonl_segments(tmp_path, "metrics.jsonl")] == list(range(1, 11))
    assert [e["episode_index"] for e in read_jsonl_segments(tmp_path, "episodes.jsonl")] == list(range(40))


def test_truncation_keeps_rows_without_an_iteration_and_drops_an_unfinished_line(tmp_path):
    (tmp_path / "e.jsonl").write_text('{"iteration": 1}\n{"note": "kept"}\n{"iteration": 2}\n{"iteration": 3')
    assert truncate_after_iteration(tmp_path, "e.jsonl", 1) == 1
    assert (tmp_path / "e.jsonl").read_text() == '{"iteration": 1}\n{"note": "kept"}\n'
    assert truncate_after_iteration(tmp_path, "absent.jsonl", 1) == 0


def _scalars(tb_dir, tag):
    """TensorBoard's own reading of a run directory (event files in name order, purges applied)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tb_dir))
    acc.Reload()
    return [(e.step, e.value) for e in acc.Scalars(tag)]


def _scalars_per_file(tb_dir, tag):
    """Every event file read alone, oldest first. Files written within one second by one process
    differ only in a counter that does not sort as text (9 < 10), so the test reads them by age."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = []
    for f in sorted(Path(tb_dir).glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime_ns):
        acc = EventAccumulator(str(f))
        acc.Reload()
        if tag in acc.Tags()["scalars"]:
            out += [(e.step, e.value) for e in acc.Scalars(tag)]
    return out


def test_tensorboard_hides_the_redone_iterations_after_a_resume(tmp_path):
    writer = MetricsWriter(tmp_path, tensorboard=True, rotate_mb=None)
    _write_run(tmp_path, range(1, 9), writer)
    writer.close()
    time.sleep(1.1)  # a resumed run is a later process: its event file's name sorts after the first one's
    writer = MetricsWriter(tmp_path, tensorboard=True, resume_iteration=5, rotate_mb=None)
    for it in (6, 7):
        writer.scalars({**_metrics_row(it), "loss": 2.0})
    writer.close()
    assert _scalars(tmp_path / "tb", "loss") == [(100 * i, 0.5) for i in range(1, 6)] + [(600, 2.0), (700, 2.0)]


def test_tensorboard_event_files_rotate_within_their_budget(tmp_path):
    limit, keep = 4_000, 2
    writer = MetricsWriter(tmp_path, tensorboard=True, rotate_mb=limit / 2**20, keep=keep)
    for it in range(1, 61):  # about 15 kB of events: 3 rotations
        writer.scalars(_metrics_row(it))
    writer.close()
    files = sorted((tmp_path / "tb").glob("events.out.tfevents.*"))
    assert len(files) == keep + 1
    assert sum(p.stat().st_size for p in files) <= (keep + 1) * (limit + 500)  # one row's events past the limit
    steps = [s for s, _ in _scalars_per_file(tmp_path / "tb", "loss")]
    assert steps[-1] == 6_000 and steps == sorted(steps) and 20 < len(steps) < 60
    # files left by restarts are small: they stay while the closed files fit in keep * limit
    for _ in range(4):
        MetricsWriter(tmp_path, tensorboard=True, rotate_mb=1.0, keep=keep).close()
    assert len(list((tmp_path / "tb").glob("events.out.tfevents.*"))) == keep + 1 + 4


def test_config_keys_defaults_and_errors():
    cfg = load_config("configs/smoke.yaml")
    assert (cfg.runtime.log_rotate_mb, cfg.runtime.log_keep) == (64.0, 5)
    assert (RuntimeConfig().log_rotate_mb, RuntimeConfig().log_keep) == (64.0, 5)
    off = load_config("configs/smoke.yaml", ["runtime.log_rotate_mb=null", "runtime.log_keep=0"])
    assert (off.runtime.log_rotate_mb, off.runtime.log_keep) == (None, 0)
    with pytest.raises(ConfigError, match=r"runtime\.log_rotate_mb=0\.0 must be > 0 \(null: never rotate\)"):
        load_config("configs/smoke.yaml", ["runtime.log_rotate_mb=0"])
    with pytest.raises(ConfigError, match=r"runtime\.log_rotate_mb=-2\.0 must be > 0"):
        load_config("configs/smoke.yaml", ["runtime.log_rotate_mb=-2"])
    with pytest.raises(ConfigError, match=r"runtime\.log_keep=-1 must be >= 0"):
        load_config("configs/smoke.yaml", ["runtime.log_keep=-1"])
    with pytest.raises(ConfigError, match=r"runtime\.log_keep: expected an integer"):
        load_config("configs/smoke.yaml", ["runtime.log_keep=2.5"])
    with pytest.raises(ValueError, match="rotate_bytes=0"):
        JsonlLog("unused.jsonl", rotate_bytes=0)
