"""One writer per run: a second driver of a run is refused with a message naming the first, a dead
driver's lease is taken over (at once on its own host, after its TTL from elsewhere), and a driver
whose lease was taken over stops without writing on."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from covers_dist.runtime.driver import LeaseHeld, Trainer
from covers_dist.runtime.lease import LEASE, RunLease
from covers_dist.storage import Storage

from test_runtime_serial import TINY, tiny_cfg

REPO = Path(__file__).resolve().parents[1]


def foreign(store: Storage, renewals: int = 0, host: str = "elsewhere", pid: int = 4242) -> dict:
    """Write another driver's lease (id ``other``) into ``store``, renewed ``renewals`` times."""
    lease = {"id": "other", "host": host, "pid": pid, "started": time.time(), "renewed": time.time(), "renewals": renewals}
    store.write_bytes(LEASE, json.dumps(lease).encode())
    return lease


def test_a_renewed_lease_from_another_host_is_refused_and_an_unrenewed_one_expires(tmp_path):
    store = Storage(tmp_path)
    foreign(store)
    stop = threading.Event()

    def renew():
        n = 0
        while not stop.wait(0.1):
            n += 1
            foreign(store, renewals=n)

    keeper = threading.Thread(target=renew, daemon=True)
    keeper.start()
    try:
        with pytest.raises(LeaseHeld, match=r"another driver holds this run: PID 4242 on host elsewhere"):
            RunLease(store, ttl_s=1.0, log=lambda *_: None).acquire()
    finally:
        stop.set()
        keeper.join()
    notes = []
    start = time.monotonic()
    mine = RunLease(store, ttl_s=1.0, log=notes.append).acquire()  # nobody renews it now
    assert 0.9 <= time.monotonic() - start < 5
    assert any("had expired" in n for n in notes)
    assert json.loads(store.read_bytes(LEASE))["id"] == mine.id
    mine.release()
    assert not store.exists(LEASE)


def test_a_lease_left_by_a_dead_process_of_this_host_is_taken_at_once(tmp_path):
    store = Storage(tmp_path)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    foreign(store, host=os.uname().nodename, pid=dead.pid)
    start = time.monotonic()
    RunLease(store, ttl_s=30.0, log=lambda *_: None).acquire().release()
    assert time.monotonic() - start < 5


def test_a_driver_that_lost_its_lease_stops_without_writing_on(tmp_path):
    store = Storage(tmp_path)
    lease = RunLease(store, ttl_s=0.6, log=lambda *_: None).acquire()
    foreign(store)  # another driver took the run over while this one stalled
    deadline = time.monotonic() + 5
    while not lease.lost and time.monotonic() < deadline:
        time.sleep(0.05)
    assert lease.lost
    with pytest.raises(LeaseHeld, match="lost the run's lease to PID 4242 on host elsewhere"):
        lease.check()
    lease.release()
    assert json.loads(store.read_bytes(LEASE))["id"] == "other"  # not its to remove


def test_a_second_trainer_of_one_run_in_one_process_is_refused(tmp_path):
    cfg = tiny_cfg(tmp_path)
    first = Trainer(cfg, log=lambda *_: None)
    try:
        with pytest.raises(LeaseHeld, match=f"PID {os.getpid()}"):
            Trainer(cfg, log=lambda *_: None)
    finally:
        first.close()
    Trainer(cfg, log=lambda *_: None).close()  # given back: the next one takes it


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "covers_dist.cli", "train", *args]


def test_two_drivers_on_one_run_and_a_killed_driver(tmp_path):
    """A real driver process trains; a second `train --resume` and a second `train --overwrite` of the
    same run are refused naming it, and leave its checkpoints alone; once it is SIGKILLed, a resume
    takes the run at once (its lease names a process of this host that is gone)."""
    run_dir = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    sets = [a for s in [*TINY, "runtime.total_env_steps=10000000", "runtime.checkpoint_every=1"] for a in ("--set", s)]
    first = subprocess.Popen(
        _cli("--config", "configs/smoke.yaml", "--run-dir", str(run_dir), *sets),
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not list((run_dir / "checkpoints").glob("ckpt-*")):
            assert first.poll() is None, first.stderr.read()
            assert time.monotonic() < deadline, "the first driver wrote no checkpoint in 120 s"
            time.sleep(0.2)
        for argv in (["--resume", str(run_dir)], ["--config", "configs/smoke.yaml", "--run-dir", str(run_dir), "--overwrite"]):
            second = subprocess.run(_cli(*argv), cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
            assert second.returncode == 2, second.stderr
            assert f"another driver holds this run: PID {first.pid} on host" in second.stderr, second.stderr
            assert list((run_dir / "checkpoints").glob("ckpt-*")), "the refused driver cleared the run"
        assert first.poll() is None  # still training
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait(30)
    assert Storage(run_dir).exists(LEASE)  # a killed driver leaves its lease behind
    from covers_dist.config import load_run_config

    start = time.monotonic()
    resumed = Trainer(load_run_config(run_dir / "config.yaml"), resume=True, log=lambda *_: None)
    resumed.close()
    assert time.monotonic() - start < 60  # taken at once, not after the 60-s TTL
