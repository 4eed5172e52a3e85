"""`covers-dist train` as a user runs it: a real process, SIGTERM + resume, and `ray job submit`
against a loopback-only head started (and stopped, by PID) by the test."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXE = str(Path(sys.executable).parent / "covers-dist")
SMALL = ["--set", "env.episodes_per_task=8", "--set", "env.max_episode_steps=50", "--set", "clustering.update_every=8", "--set", "ppo.epochs=1",
         "--set", "runtime.log_every_s=0.5"]


def _env():
    env = dict(os.environ)
    env["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    env.pop("RAY_ADDRESS", None)
    env["PATH"] = f"{Path(sys.executable).parent}:{env.get('PATH', '')}"
    return env


def _lines(path):
    return [json.loads(x) for x in path.read_text().splitlines()] if path.is_file() else []


def test_sigterm_checkpoints_and_resume_continues(tmp_path):
    run = tmp_path / "run"
    cmd = [EXE, "train", "--config", "configs/smoke.yaml", "--serial", "--run-dir", str(run), *SMALL,
           "--set", "runtime.total_env_steps=4000", "--set", "runtime.checkpoint_every=100"]
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
    assert 2 <= stopped_at < 10
    res = subprocess.run([EXE, "train", "--resume", str(run)], cwd=ROOT, env=_env(), capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"resumed from" in res.stdout and "finished" in res.stdout
    rows = _lines(run / "metrics.jsonl")
    assert [r["iteration"] for r in rows] == list(range(1, 11))
    episodes = _lines(run / "episodes.jsonl")
    assert [e["episode_index"] for e in episodes] == list(range(80))


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


def test_bad_config_is_a_clear_error(tmp_path):
    res = subprocess.run([EXE, "train", "--set", "ppo.epochs=-1"], cwd=ROOT, env=_env(), capture_output=True, text=True)
    assert res.returncode == 2 and "ppo.epochs=-1 must be >= 1" in res.stderr
    res = subprocess.run([EXE, "train", "--resume", str(tmp_path)], cwd=ROOT, env=_env(), capture_output=True, text=True)
    assert res.returncode != 0 and "not a run directory" in res.stderr


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ray_job_submit_against_a_local_head(tmp_path):
    import secrets

    bindir = Path(sys.executable).parent
    temp = Path("/tmp") / f"covers-head-{os.getpid()}"
    token = tmp_path / "auth_token"  # Ray's token authentication, with a token of this test's own
    token.write_text(secrets.token_hex(32))
    env = {**_env(), "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(token)}
    port, dash = _free_port(), _free_port()
    # own ports for every agent: another Ray instance (e.g. the suite's) may hold the defaults
    agent_ports = [f"--dashboard-agent-listen-port={_free_port()}", f"--dashboard-agent-grpc-port={_free_port()}",
                   f"--runtime-env-agent-port={_free_port()}", f"--metrics-export-port={_free_port()}",
                   f"--ray-client-server-port={_free_port()}"]
    head = subprocess.run(
        [str(bindir / "ray"), "start", "--head", "--num-cpus", "2", "--node-ip-address=127.0.0.1",
         f"--port={port}", f"--dashboard-port={dash}", "--dashboard-host=127.0.0.1", "--include-dashboard=true",
         f"--temp-dir={temp}", "--disable-usage-stats", *agent_ports],
        env=env, capture_output=True, text=True, timeout=120,
    )
    assert head.returncode == 0, head.stdout + head.stderr
    try:
        for attempt in range(20):  # the head's job agent needs a few seconds after `ray start`
            job = subprocess.run(
                [str(bindir / "ray"), "job", "submit", "--address", f"http://127.0.0.1:{dash}", "--working-dir", ".",
                 "--", "covers-dist", "train", "--config", "configs/smoke.yaml", "--run-dir", str(tmp_path / "job"),
                 *SMALL, "--set", "runtime.total_env_steps=1200"],
                cwd=ROOT, env=env, capture_output=True, text=True, timeout=900,
            )
            if "No available agent" not in job.stderr + job.stdout:
                break
            time.sleep(3)
        print(job.stdout[-3000:])
        assert job.returncode == 0, job.stdout[-5000:] + job.stderr[-3000:]
        assert "succeeded" in job.stdout and "steps/s" in job.stdout and "finished" in job.stdout
    finally:
        _stop_head(temp)


def _head_pids(temp: Path) -> list[int]:
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(temp) in cmd and int(entry.name) != os.getpid():
            pids.append(int(entry.name))
    return pids


def _stop_head(temp: Path):
    """Stop only the processes of the head this test started (found by its temp dir), by PID."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in _head_pids(temp):
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        time.sleep(3)
