"""`covers-dist train` as a user runs it: a real process, SIGTERM + resume (`ray job submit` against a
local head: tests/test_head_cmd.py)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXE = str(Path(sys.executable).parent / "covers-dist")
SMALL = ["--set", "env.episodes_per_task=8", "--set", "env.max_episode_steps=50", "--set", "clustering.update_every=8", "--set", "ppo.epochs=1",
         "--set", "runtime.log_every_s=0.5", "--set", "network.channels=[2,4]", "--set", "network.hidden=8",
         "--set", "env.image_size=16"]


def _env():
    env = dict(os.environ)
    env["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    env.pop("RAY_ADDRESS", None)
    env["PATH"] = f"{Path(sys.executable).parent}:{env.get('PATH', '')}"
    return env


def _lines(path):
    return [json.loads(x) for x in path.read_text().splitlines()] if path.is_file() else []


@pytest.mark.slow
def test_sigterm_checkpoints_and_resume_continues(tmp_path):
    """The whole round trip as a user makes it: two processes. The default suite keeps the same signal
    in process (tests/test_runtime_serial.py: checkpointed, resumed, equal to the unbroken run) and a
    SIGTERM to a starting `covers-dist train` process (below)."""
    run = tmp_path / "run"
    cmd = [EXE, "train", "--config", "configs/smoke.yaml", "--serial", "--run-dir", str(run), *SMALL,
           "--set", "runtime.total_env_steps=2400", "--set", "runtime.checkpoint_every=100"]  # 6 iterations
    proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 240
    while len(_lines(run / "metrics.jsonl")) < 2:
        assert proc.poll() is None, proc.stdout.read()
        assert time.time() < deadline, "training made no progress"
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=240)
    assert proc.returncode == 0, out
    assert "interrupted" in out and "--resume" in out
    done = _lines(run / "metrics.jsonl")
    stopped_at = done[-1]["iteration"]
    assert 2 <= stopped_at < 6
    res = subprocess.run([EXE, "train", "--resume", str(run)], cwd=ROOT, env=_env(), capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"resumed from" in res.stdout and "finished" in res.stdout
    rows = _lines(run / "metrics.jsonl")
    assert [r["iteration"] for r in rows] == list(range(1, 7))
    episodes = _lines(run / "episodes.jsonl")
    assert [e["episode_index"] for e in episodes] == list(range(48))


def test_sigterm_during_start_up_stops_gracefully_before_the_first_iteration(tmp_path):
    run = tmp_path / "run"
    cmd = [EXE, "train", "--config", "configs/smoke.yaml", "--serial", "--run-dir", str(run), *SMALL,
           "--set", "runtime.total_env_steps=4000"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 120
    while not (run / "config.yaml").is_file():  # the run has started: its Trainer exists, no iteration yet
        assert proc.poll() is None and time.time() < deadline, proc.stdout.read() if proc.poll() is not None else ""
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=240)
    assert proc.returncode == 0, out  # not killed by the signal
    assert "interrupted" in out
    assert len(_lines(run / "metrics.jsonl")) <= 1


def test_bad_config_is_a_clear_error(tmp_path, capsys):
    """In this process (the CLI's main, as the console script calls it): nothing starts."""
    from covers_dist.cli import main

    assert main(["train", "--set", "ppo.epochs=-1"]) == 2
    assert "ppo.epochs=-1 must be >= 1" in capsys.readouterr().err
    assert main(["train", "--resume", str(tmp_path)]) != 0
    assert "not a run directory" in capsys.readouterr().err
