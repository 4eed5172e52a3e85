"""Storage faults survived: an object store that goes away and comes back within the retry budget
changes nothing; one that stays away, or a full disk, stops the run cleanly with a clear message
and its last valid checkpoint intact, and a resume afterwards ends where an unbroken run ends."""

from __future__ import annotations

import json
import subprocess
import threading
import uuid

import pytest
from s3_server import Gate, s3_server

from covers_dist.runtime.checkpoint import latest_valid_checkpoint, verify_checkpoint
from covers_dist.runtime.driver import Trainer

from test_runtime_serial import assignments, learner_weights, same_weights, tiny_cfg


def losses(run_dir):
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [r["iteration"] for r in rows], [r.get("ppo/policy_loss") for r in rows]


def ends_as_unbroken(trainer, run_dir, unbroken):
    """The finished ``trainer`` of ``run_dir`` ended where conftest.py's unbroken run ended."""
    same_weights(learner_weights(trainer), unbroken[1])
    assert assignments(trainer) == unbroken[0]
    assert losses(run_dir) == losses(unbroken[2])


def resume_ends_as_unbroken(cfg, run_dir, unbroken):
    """``train --resume`` of the run of ``cfg`` finishes where the unbroken run ended."""
    resumed = Trainer(cfg, resume=True, log=lambda *_: None)
    try:
        assert resumed.run()["status"] == "finished"
        ends_as_unbroken(resumed, run_dir, unbroken)
    finally:
        resumed.close()


@pytest.fixture(scope="module")
def s3():
    with s3_server() as server:
        yield server


def bucket(s3, gate) -> str:
    """A fresh bucket on the S3 server, as a storage URI through ``gate``."""
    name = f"runs-{uuid.uuid4().hex[:12]}"
    s3.make_bucket(name)
    return s3.uri(f"{name}/run", gate.port)


def _run(cfg, hook_at=None, hook=None):
    lines: list[str] = []
    trainer = Trainer(cfg, log=lines.append)
    if hook is not None:
        trainer.on_iteration.append(lambda: trainer.iteration == hook_at and hook())
    return trainer, trainer.run(), lines


def test_an_s3_outage_within_the_retry_budget_changes_nothing(s3, tiny_serial_run, tmp_path, capfd):
    gate = Gate(s3.port)
    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=1600", "runtime.checkpoint_every=1", "runtime.storage_retry_s=120",
                   f"runtime.storage={bucket(s3, gate)}")  # fmt: skip

    def outage():
        gate.close()
        threading.Timer(10.0, gate.open).start()  # back 10 s later: longer than pyarrow's own retries

    try:
        trainer, result, _ = _run(cfg, 2, outage)
        try:
            assert result["status"] == "finished"
            ends_as_unbroken(trainer, tmp_path, tiny_serial_run)
        finally:
            trainer.close()
    finally:
        gate.close()
    err = capfd.readouterr().err
    assert "failed (" in err and "retry 1 in" in err  # the outage was met, and each retry logged


def test_a_lasting_s3_outage_stops_cleanly_and_a_resume_ends_as_the_unbroken_run(s3, tiny_serial_run, tmp_path, capfd):
    gate = Gate(s3.port)
    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=1600", "runtime.checkpoint_every=1", "runtime.storage_retry_s=8",
                   f"runtime.storage={bucket(s3, gate)}")  # fmt: skip
    try:
        trainer, result, lines = _run(cfg, 2, gate.close)  # gone for good (longer than storage_retry_s)
        trainer.close()
        assert result["status"] == "storage-fault" and "StorageUnavailable" in result["error"]
        assert "kept failing for 8 s" in result["error"]
        stop = [line for line in lines if line.startswith("stopped by a storage fault at iteration 2")]
        assert stop and "covers-dist train --resume" in stop[0], lines[-3:]
        assert "retry 1 in" in capfd.readouterr().err  # each retry was logged
        ckpt = latest_valid_checkpoint(tmp_path, log=lambda *_: None)
        assert ckpt is not None and result["checkpoint"] == str(ckpt)
        verify_checkpoint(ckpt)
        gate.open()  # the storage is back
        resume_ends_as_unbroken(cfg, tmp_path, tiny_serial_run)
    finally:
        gate.close()


@pytest.fixture
def small_disk(tmp_path):
    """A 16 MiB tmpfs mounted for the test (root only)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(mount)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip()}): needs root")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], check=True)


def fill(disk) -> None:
    """Write a ballast file until the disk has no room left."""
    chunk = b"\0" * 65536
    with open(disk / "ballast", "wb") as fh:
        try:
            while True:
                fh.write(chunk)
                fh.flush()
        except OSError:
            pass


def test_a_full_disk_stops_cleanly_and_a_resume_ends_as_the_unbroken_run(small_disk, tiny_serial_run):
    run_dir = small_disk / "run"
    cfg = tiny_cfg(run_dir, "runtime.total_env_steps=1600", "runtime.checkpoint_every=1")
    trainer, result, lines = _run(cfg, 2, lambda: fill(small_disk))
    trainer.close()
    assert result["status"] == "storage-fault" and "No space left on device" in result["error"], result
    assert any(line.startswith("stopped by a storage fault at iteration 2") for line in lines)
    ckpt = latest_valid_checkpoint(run_dir, log=lambda *_: None)
    assert ckpt is not None and ckpt.name == "ckpt-000001"  # ckpt 2 found no room: the one before stands
    verify_checkpoint(ckpt)
    assert not list((run_dir / "checkpoints").glob(".tmp-*"))  # no half-written checkpoint left behind
    (small_disk / "ballast").unlink()  # room again
    resume_ends_as_unbroken(cfg, run_dir, tiny_serial_run)
