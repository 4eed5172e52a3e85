"""A run's storage (runtime.storage): local paths and URIs through pyarrow.fs, one S3 server on
127.0.0.1 (moto's server mode), objects written whole, and a checkpoint's manifest that covers
what a restore needs."""

import json
import shutil

import pytest
from s3_server import s3_server

from covers_dist.config import ConfigError, load_config
from covers_dist.runtime.checkpoint import CheckpointError, list_checkpoints, verify_checkpoint
from covers_dist.runtime.run_storage import mirrors_run_dir
from covers_dist.storage import Storage, StorageError, pack_dir, storage_child, unpack_dir


def _round_trip(store: Storage) -> None:
    assert not store.exists("a/b.bin") and store.list("a") == [] and store.list_dirs("") == []
    store.write_bytes("a/b.bin", b"one")
    store.write_bytes("a/b.bin", b"two")  # replaced whole
    store.write_bytes("a/c/d.json", b"{}")
    assert store.read_bytes("a/b.bin") == b"two" and store.exists("a/b.bin")
    assert store.list("a") == ["b.bin"] and store.list("a", recursive=True) == ["b.bin", "c/d.json"]
    assert store.list_dirs("") == ["a"] and store.list_dirs("a") == ["c"]
    with pytest.raises(StorageError, match="a/missing.bin is missing"):
        store.read_bytes("a/missing.bin")
    store.delete("a/b.bin")
    store.delete("a/b.bin")  # a missing object: nothing to do
    assert store.list("a", recursive=True) == ["c/d.json"]
    store.delete_dir("a")
    store.delete_dir("a")
    assert store.list("", recursive=True) == []


def test_local_storage_round_trip_leaves_no_temporary_file(tmp_path):
    store = Storage(tmp_path / "store")
    _round_trip(store)
    store.write_bytes("x/y.bin", b"z")
    assert sorted(p.name for p in (tmp_path / "store" / "x").iterdir()) == ["y.bin"]  # written through a rename
    assert Storage(f"file://{tmp_path}/store").read_bytes("x/y.bin") == b"z"  # the same place by URI


def test_s3_storage_round_trip_and_a_missing_bucket_named():
    with s3_server() as s3:
        s3.make_bucket("covers-runs")
        _round_trip(Storage(s3.uri("covers-runs/run-1")))
        with pytest.raises(StorageError, match="s3://no-such-bucket/x/key is missing"):
            Storage(s3.uri("no-such-bucket/x")).read_bytes("key")


def test_put_dir_writes_the_manifest_last_and_get_dir_copies_back(tmp_path):
    src = tmp_path / "ckpt"
    (src / "learners").mkdir(parents=True)
    for name in ("manifest.json", "driver.json", "learners/policy-0.pt"):
        (src / name).write_text(name)
    written = []
    store = Storage(tmp_path / "store")
    original = store.write_bytes
    store.write_bytes = lambda key, data: (written.append(key), original(key, data))  # type: ignore[method-assign]
    store.put_dir(src, "checkpoints/ckpt-1", last="manifest.json")
    assert written[-1] == "checkpoints/ckpt-1/manifest.json" and len(written) == 3
    assert store.get_dir("checkpoints/ckpt-1", tmp_path / "back") == ["driver.json", "learners/policy-0.pt", "manifest.json"]
    assert (tmp_path / "back" / "learners" / "policy-0.pt").read_text() == "learners/policy-0.pt"


def test_pack_unpack_round_trip_and_refuses_names_outside(tmp_path):
    (tmp_path / "a" / "sub").mkdir(parents=True)
    (tmp_path / "a" / "x.json").write_text("1")
    (tmp_path / "a" / "sub" / "y.npz").write_bytes(b"\0\1")
    assert unpack_dir(pack_dir(tmp_path / "a"), tmp_path / "b") == ["sub/y.npz", "x.json"]
    assert (tmp_path / "b" / "sub" / "y.npz").read_bytes() == b"\0\1"
    import io
    import tarfile

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        info = tarfile.TarInfo("../escape")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(StorageError, match="refusing archive member '../escape'"):
        unpack_dir(buf.getvalue(), tmp_path / "c")
    assert not (tmp_path / "escape").exists()


def test_storage_config_is_checked_and_named_in_errors(tmp_path):
    with pytest.raises(ConfigError, match="unknown scheme 'ftp'"):
        load_config("configs/smoke.yaml", ["runtime.storage=ftp://host/x"])
    with pytest.raises(ConfigError, match="runtime.storage is empty"):
        load_config("configs/smoke.yaml", ["runtime.storage= "])
    with pytest.raises(StorageError, match="cannot open storage s3://b/x: .*'bogus'"):
        Storage("s3://b/x?bogus=1")
    assert storage_child("s3://b/run?scheme=http", "clean") == "s3://b/run/clean?scheme=http"
    same = load_config("configs/smoke.yaml", [f"runtime.run_dir={tmp_path}", f"runtime.storage=file://{tmp_path}"])
    apart = load_config("configs/smoke.yaml", [f"runtime.run_dir={tmp_path}", f"runtime.storage={tmp_path}/copy"])
    assert not mirrors_run_dir(same) and mirrors_run_dir(apart)
    assert not mirrors_run_dir(load_config("configs/smoke.yaml", [f"runtime.run_dir={tmp_path}"]))


def test_a_checkpoint_without_its_bank_does_not_verify(tiny_serial_run, tmp_path):
    """The manifest must list what a restore reads, the bank included: a checkpoint whose bank is
    missing (and whose manifest does not name it) is refused by name, not restored half."""
    ckpt = tmp_path / "ckpt"
    shutil.copytree(list_checkpoints(tiny_serial_run[2])[-1], ckpt)
    verify_checkpoint(ckpt)
    shutil.rmtree(ckpt / "bank")
    manifest = json.loads((ckpt / "manifest.json").read_text())
    manifest["files"] = {k: v for k, v in manifest["files"].items() if not k.startswith("bank/")}
    (ckpt / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(CheckpointError, match="the manifest lacks bank/bank.json, which a restore needs"):
        verify_checkpoint(ckpt)


def test_an_actor_that_cannot_read_the_drivers_token_stops_with_the_reason(tmp_path):
    from covers_dist.runtime.run_storage import check_reachable, mark_run

    token = mark_run(str(tmp_path / "run"))
    check_reachable(str(tmp_path / "run"), token, "the learner of policy 0")  # sees it: nothing happens
    check_reachable(str(tmp_path / "elsewhere"), None, "a serial run")  # no token: nothing to check
    with pytest.raises(StorageError, match=r"the learner of policy 0 on host .* does not see .*run.json is missing"):
        check_reachable(str(tmp_path / "elsewhere"), token, "the learner of policy 0")  # a disk only the driver has
    mark_run(str(tmp_path / "run"))  # a newer driver of the same storage
    with pytest.raises(StorageError, match="belongs to another run"):
        check_reachable(str(tmp_path / "run"), token, "rollout worker 0")


def test_checkpoint_copies_carry_the_logs_but_never_a_drivers_token(tmp_path):
    """The storage apart from the run directory gets the checkpoint (manifest last) and the logs;
    the token of the running driver there is never overwritten by a copy, and a driver on a fresh
    node fetches the newest valid checkpoint and the logs but not an earlier driver's token."""
    from covers_dist.runtime.run_storage import RUN_MARKER, fetch_run, mark_run, push_checkpoint

    run_dir, store_dir = tmp_path / "run", tmp_path / "store"
    cfg = load_config("configs/smoke.yaml", [f"runtime.run_dir={run_dir}", f"runtime.storage={store_dir}"])
    ckpt = run_dir / "checkpoints" / "ckpt-000001"
    (ckpt / "bank").mkdir(parents=True)
    (run_dir / "metrics.jsonl").write_text('{"iteration": 1}\n')
    (run_dir / RUN_MARKER).write_text('{"token": "stale"}')  # e.g. fetched from an earlier driver
    token = mark_run(str(store_dir))
    for name in ("driver.json", "config.yaml", "bank/bank.json"):
        (ckpt / name).write_text("{}" if name == "driver.json" else "x")
    from covers_dist.clustering.persistence import file_sha256

    files = {n: file_sha256(ckpt / n) for n in ("driver.json", "config.yaml", "bank/bank.json")}
    (ckpt / "manifest.json").write_text(json.dumps({"format_version": 1, "iteration": 1, "files": files}))
    push_checkpoint(cfg, ckpt)
    store = Storage(store_dir)
    assert json.loads(store.read_bytes(RUN_MARKER))["token"] == token
    assert store.read_bytes("metrics.jsonl") == b'{"iteration": 1}\n'
    assert store.list("checkpoints/ckpt-000001", recursive=True) == ["bank/bank.json", "config.yaml", "driver.json", "manifest.json"]

    shutil.rmtree(run_dir)  # a fresh node
    got = fetch_run(cfg, log=lambda *_: None)
    assert got == run_dir / "checkpoints" / "ckpt-000001" and verify_checkpoint(got)["iteration"] == 1
    assert (run_dir / "metrics.jsonl").is_file() and not (run_dir / RUN_MARKER).exists()
