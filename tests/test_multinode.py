"""Nodes that share no disk, and a run's storage on an S3 server (``pytest -m multinode``, as root).

* A 2-node loopback cluster whose second node runs in its own mount namespace with an empty tmpfs
  over the run directories (``covers-dist bench chaos --node-loss ... --isolated-disk``): the
  rollout workers or the learners run there, write their state only through the run's storage
  (an S3 server on 127.0.0.1), are killed with their node mid-run, come back on the head from
  that storage, and the run ends equal to the clean run.
* A run whose storage is that S3 server: checkpointed, its driver's disk lost, resumed from the
  URI alone (``train --resume s3://...``), it ends where the uninterrupted run ends.
"""

import shutil

import pytest
from s3_server import s3_server
from test_chaos import _assert_passed, _chaos, _sets
from test_runtime_serial import tiny_cfg

from covers_dist.bench.chaos import compare, final_state
from covers_dist.cli import main
from covers_dist.runtime.driver import Trainer, train
from covers_dist.storage import Storage

ROOT_ONLY = pytest.mark.skipif(shutil.which("unshare") is None, reason="needs unshare (util-linux)")


@pytest.mark.multinode
@ROOT_ONLY
@pytest.mark.parametrize("lose", ["workers", "learners"])
def test_losing_a_node_that_shares_no_disk_changes_nothing(lose):
    with s3_server() as s3:
        s3.make_bucket("covers-runs")
        storage = s3.uri(f"covers-runs/node-loss-{lose}")
        report, _ = _chaos("--node-loss", lose, "--isolated-disk", "--set", f"runtime.storage={storage}",
                           *_sets("runtime.total_env_steps=4000"))  # fmt: skip
        n = report["node_loss"]
        assert n["node_removed"] and n["isolated_disk"]
        wanted = "worker-" if lose == "workers" else "learner-"
        lost = [name for name in n["on_lost_node"] if name.startswith(wanted)]
        assert lost and set(lost) <= set(n["moved_to_head"]), n  # ran on the isolated node, came back on the head
        _assert_passed(report)
        store = Storage(storage)
        assert store.exists("node-loss/clustering_live/state.tar") and store.list("node-loss/learners_live")


@pytest.mark.multinode
@ROOT_ONLY
def test_a_storage_the_isolated_node_cannot_see_stops_the_run_with_the_reason(tmp_path):
    """The same cluster with the storage a path under the hidden directory (file://): the workers
    placed on the isolated node cannot read the driver's token there and stop at once, naming
    the storage and the fix, instead of keeping their state where no restart would find it."""
    import subprocess
    import sys

    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "covers_dist", "bench", "chaos", "--node-loss", "workers", "--isolated-disk",
         "--out", str(out), "--set", f"runtime.storage=file://{out}/store", *_sets("runtime.total_env_steps=4000")],
        capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert done.returncode != 0
    assert "does not see this run's storage" in done.stderr and "run.json is missing" in done.stderr, done.stderr[-3000:]


@pytest.mark.multinode
def test_checkpoint_and_resume_through_an_s3_uri_equal_the_uninterrupted_run(tiny_serial_run, tmp_path):
    with s3_server() as s3:
        s3.make_bucket("covers-runs")
        uri = s3.uri("covers-runs/tiny")
        run_dir = tmp_path / "driver-disk"
        cfg = tiny_cfg(run_dir, "runtime.total_env_steps=1600", "runtime.checkpoint_every=1", f"runtime.storage={uri}")
        first = Trainer(cfg, log=lambda *_: None)
        first.on_iteration.append(lambda: setattr(first, "_stop", first.iteration >= 2))  # stopped as by a signal
        try:
            assert first.run()["status"] == "interrupted"
        finally:
            first.close()
        store = Storage(uri)
        assert store.list_dirs("checkpoints") == ["ckpt-000001", "ckpt-000002"]
        assert {"config.yaml", "metrics.jsonl", "episodes.jsonl"} <= set(store.list(""))
        assert store.exists("clustering_live/state.tar") and store.exists("processes/driver.json")
        shutil.rmtree(run_dir)  # the driver's node is gone, and its disk with it

        assert train(resume_dir=uri, log=lambda *_: None)["status"] == "finished"
        c = compare(final_state(tiny_serial_run[2]), final_state(run_dir))
        assert c["assignments_identical"] and c["weights_identical"] and c["weights_max_abs_diff"] == 0.0, c
        assert c["logged_exactly_once"], c
        assert store.list_dirs("checkpoints")[-1] == "ckpt-000004"


def test_an_isolated_disk_needs_node_loss_and_a_storage_uri(tmp_path, capsys):
    for args, words in (
        (["--isolated-disk"], "--isolated-disk goes with --node-loss"),
        (["--node-loss", "workers", "--isolated-disk"], "--isolated-disk needs --set runtime.storage=URI"),
        (["--node-loss", "workers", "--isolated-disk", "--set", f"runtime.storage={tmp_path}"], "cannot see a local path"),
    ):
        with pytest.raises(SystemExit) as exc:
            main(["bench", "chaos", "--config", "configs/smoke.yaml", "--out", str(tmp_path / "out"), *args])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and words in err, (args, err)
