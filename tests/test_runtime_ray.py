"""The COVERS loop on real Ray actors (ray.init(num_cpus=2), loopback only): parity with serial
mode, and fault tolerance of the rollout workers and the clustering actor."""

import threading
import time

import pytest

from covers_dist.runtime.driver import Trainer

from test_runtime_serial import tiny_cfg


def _ray_cfg(tmp_path, *extra):
    return tiny_cfg(tmp_path, "runtime.serial=false", *extra)


# parity with serial mode (the same assignments and bit-identical weights, on the same config):
# tests/test_pipeline.py::test_ray_pipelined_run_equals_the_serial_pipelined_run


@pytest.mark.slow
def test_killed_worker_and_clustering_actor_come_back_without_losing_or_doubling(ray_local, tmp_path):
    """One run (one set of actors to start): a rollout worker killed while it samples restarts, then
    the clustering actor killed between iterations comes back with the same bank; no episode is
    lost or assigned twice. Slow tier: the default suite's chaos test
    (tests/test_chaos.py::test_short_chaos_run_equals_the_clean_run) kills a worker and the
    clustering actor in one run and checks every episode assigned and logged exactly once and the
    run equal to the clean one; this one adds a kill timed into sampling."""
    import ray

    trainer = Trainer(_ray_cfg(tmp_path, "runtime.total_env_steps=2000"), log=lambda *_: None)
    try:
        trainer.start_policy(0)
        trainer.step()
        victim = trainer.backend.workers[0]
        old_worker = ray.get(victim.pid.remote())
        killer = threading.Timer(0.2, lambda: ray.kill(victim, no_restart=False))
        killer.start()
        trainer.step()  # the kill lands while this iteration samples
        killer.join()
        trainer.step()
        assert ray.get(victim.pid.remote()) != old_worker

        before = trainer.backend.call_clustering("summary")
        old_pid = trainer.backend.call_clustering("ping")
        ray.kill(trainer.backend.clustering, no_restart=False)
        deadline = time.time() + 60
        new_pid = old_pid
        while new_pid == old_pid:  # the kill is asynchronous; the restarted actor reloads its bank
            assert time.time() < deadline, "the clustering actor did not come back"
            try:
                new_pid = trainer.backend.call_clustering("ping")
            except ray.exceptions.RayActorError:
                pass
            time.sleep(0.5)
        after = trainer.backend.call_clustering("summary")
        assert after["policies"] == before["policies"] and after["assignments"] == before["assignments"] == 3
        for _ in range(2):
            trainer.step()
        recs = trainer.backend.call_clustering("assignments", 0, 100)
    finally:
        trainer.close()
    episodes = [e for r in recs for e in r["episode_indices"]]
    assert episodes == list(range(40)) and len(recs) == 5
