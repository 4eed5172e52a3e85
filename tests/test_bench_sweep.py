"""``covers-dist bench sweep``: the figures it reads from a run's metrics, and one real tiny sweep."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from covers_dist.bench.sweep import summarize, table

ROOT = Path(__file__).resolve().parents[1]


def _rows(successes, steps_per_iteration=400, seconds_per_iteration=2.0):
    return [
        {"env_steps": (i + 1) * steps_per_iteration, "wall_time": 100.0 + i * seconds_per_iteration,
         "success/reach": s, "num_policies": 1 if i < 3 else 2}
        for i, s in enumerate(successes)
    ]  # fmt: skip


def test_summary_finds_the_first_window_at_0_9_and_the_fifths():
    rows = _rows([0.0, 0.5, 1.0, 0.75, 1.0, 1.0, 0.0, 1.0, 1.0, 1.0])
    for i, row in enumerate(rows):
        row["return/reach"] = float(i)
    s = summarize(rows, "reach", window=3)
    # windows of 3: ..., (1.0, 0.75, 1.0) = 0.917 ends at the 5th iteration
    assert s["steps_to_0.9"] == 2000 and s["wall_s_to_0.9"] == 8.0
    assert s["fifths"] == [0.25, 0.875, 1.0, 0.5, 1.0] and s["final"] == 1.0
    assert s["policies"] == 2 and s["iterations"] == 10 and s["return_fifths"] == [0.5, 2.5, 4.5, 6.5, 8.5]
    never = summarize(_rows([0.0] * 6), "reach")
    assert never["steps_to_0.9"] is None and never["final"] == 0.0
    assert summarize(rows, "push")["iterations"] == 0  # a task the run never saw
    assert "| a | 0 |" in table({"task": "reach", "group": "D4", "steps": 4000, "config": "c",
                                 "runs": [{"variant": "a", "seed": 0, "wall_s": 1.0, **s}]})  # fmt: skip


def test_a_tiny_sweep_runs_each_variant_and_refuses_a_bad_one(tmp_path, capsys, monkeypatch):
    """In this process (the CLI's main, as the console script calls it); serial runs, no Ray."""
    from covers_dist.cli import main

    monkeypatch.chdir(ROOT)
    argv = ["bench", "sweep", "--config", "configs/smoke.yaml", "--task", "reach", "--steps", "800", "--serial",
            "--set", "network.channels=[2,4]", "--set", "network.hidden=8", "--json", "--out", str(tmp_path)]  # fmt: skip
    assert main([*argv, "--variant", "", "--variant", "ppo.reward_norm=none"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [r["variant"] for r in report["runs"]] == ["(as configured)", "ppo.reward_norm=none"]
    assert all(r["iterations"] == 2 and 0.0 <= r["final"] <= 1.0 for r in report["runs"])
    assert (tmp_path / "run-02" / "metrics.jsonl").is_file()
    with pytest.raises(SystemExit) as bad:  # refused before any run starts
        main([*argv, "--variant", "ppo.reward_norm=sometimes"])
    assert bad.value.code != 0 and "reward_norm" in str(bad.value.code)


def test_a_signal_stops_the_whole_sweep_not_only_the_run_in_progress(tmp_path):
    cmd = [sys.executable, "-m", "covers_dist", "bench", "sweep", "--config", "configs/smoke.yaml", "--task", "reach",
           "--steps", "40000", "--serial", "--set", "network.channels=[2,4]", "--set", "network.hidden=8",
           "--json", "--out", str(tmp_path),
           "--variant", "", "--variant", "ppo.lr=1e-3", "--variant", "ppo.epochs=1"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stderr:  # wait until the first run is training
            if "steps=" in line:
                break
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-3000:]
    report = json.loads(out.strip().splitlines()[-1])
    assert [r["variant"] for r in report["runs"]] == ["(as configured)"] and report["runs"][0]["interrupted"]
    assert "the sweep stops here" in err
    assert not (tmp_path / "run-02").exists()
