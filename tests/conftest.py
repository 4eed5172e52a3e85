"""Shared test set-up: headless rendering, loopback-only Ray and one OpenMP thread a process, set
before anything imports them."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
# One intra-op thread per process (pytest's workers and every process they start): two pytest
# workers already keep both cores busy, and a second OpenMP thread in each only oversubscribes them
# (on 2 cores the default suite took 6 min 32 s with this against 7 min 43 s without, docs/guide/testing.md).
# Components that choose their own thread count (learners, rollout workers) still set it.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def ray_local():
    """One loopback-only Ray instance (2 CPUs) shared by every test that needs Ray."""
    from covers_dist.runtime.ray_setup import init_ray, shutdown_ray

    ray = init_ray(num_cpus=2)
    yield ray
    shutdown_ray()


@pytest.fixture
def short_tmpdir():
    """A fresh directory with a short path (under /tmp where it exists), for a process given it as
    ``TMPDIR``: Ray's socket paths fit under it, so a Ray instance started there keeps its temp dir
    inside it instead of falling back to /tmp. Removed afterwards."""
    import shutil
    import tempfile
    from pathlib import Path

    path = tempfile.mkdtemp(prefix="ct-", dir="/tmp" if os.path.isdir("/tmp") else None)
    yield Path(path)
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="module")
def one_torch_thread():
    """Small tensors on 2 shared cores: one intra-op thread is faster and reproducible."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def tiny_serial_run(tmp_path_factory):
    """One serial run of tests/test_runtime_serial.py's tiny config (1600 env steps: 4 iterations,
    pipelined as by default), made once for every test that compares with it or reads it:
    ``(assignments, {policy id: weights}, run directory)``. Nothing may write into the directory."""
    from test_runtime_serial import assignments, learner_weights, tiny_cfg

    from covers_dist.runtime.driver import Trainer

    run_dir = tmp_path_factory.mktemp("tiny-serial-run")
    trainer = Trainer(tiny_cfg(run_dir, "runtime.total_env_steps=1600"), log=lambda *_: None)
    try:
        assert trainer.run()["status"] == "finished"
        return assignments(trainer), learner_weights(trainer), run_dir
    finally:
        trainer.close()


# The default suite runs on two pytest-xdist workers (`make test`: `-n 2 --dist loadfile
# --no-loadscope-reorder`), one test module at a time each. A worker that draws a long module last
# keeps the run going while the other idles, so the modules that take longest (measured, see
# docs/guide/testing.md) are handed out first and the many short ones fill in behind them. Without xdist
# the order changes nothing but the sequence.
LONGEST_FIRST = (
    "test_chaos.py",
    "test_evaluation.py",
    "test_storage_faults.py",
    "test_lease.py",
    "test_plain_shell.py",
    "test_api_ray.py",
    "test_pipeline.py",
    "test_noise.py",
    "test_models.py",
    "test_bench_learn.py",
    "test_runtime_serial.py",
    "test_assign_at.py",
    "test_ray_setup.py",
    "test_train_cli.py",
    "test_learning_metaworld.py",
    "test_metaworld_suite.py",
    "test_api_fuzz.py",
    "test_ppo.py",
    "test_bench_sweep.py",
    "test_smoke_run.py",
    "test_clustering_encoders.py",
    "test_metaworld_render.py",
    "test_offpolicy_batch.py",
    "test_rllib_module.py",
    "test_cluster_fit.py",
    "test_clustering_calibrated.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order otherwise
