"""The COVERS loop on real Ray actors (ray.init(num_cpus=2), loopback only): parity with serial
mode, and fault tolerance of the rollout workers and the clustering actor."""

import threading
import time

import pytest

from covers_dist.runtime.driver import Trainer

from test_runtime_serial import assignments, tiny_cfg


def _ray_cfg(tmp_path, *extra):
    return tiny_cfg(tmp_path, "runtime.serial=false", *extra)


def test_ray_assignments_equal_serial_assignments(ray_local, tmp_path):
    serial = Trainer(tiny_cfg(tmp_path / "s", "runtime.total_env_steps=1200"), log=lambda *_: None)
    serial.run()
    serial.close()
    distributed = Trainer(_ray_cfg(tmp_path / "r", "runtime.total_env_steps=1200"), log=lambda *_: None)
    distributed.run()
    got = assignments(distributed)
    distributed.close()
    assert got == assignments(serial)


def test_killed_rollout_worker_restarts_without_losing_or_doubling(ray_local, tmp_path):
    import ray

    trainer = Trainer(_ray_cfg(tmp_path, "runtime.total_env_steps=2000"), log=lambda *_: None)
    trainer.start_policy(0)
    trainer.step()
    victim = trainer.backend.workers[0]
    old_pid = ray.get(victim.pid.remote())
    killer = threading.Timer(0.2, lambda: ray.kill(victim, no_restart=False))
    killer.start()
    trainer.step()  # the kill lands while this iteration samples
    killer.join()
    for _ in range(3):
        trainer.step()
    new_pid = ray.get(victim.pid.remote())
    recs = trainer.backend.call_clustering("assignments", 0, 100)
    trainer.close()
    assert new_pid != old_pid
    episodes = [e for r in recs for e in r["episode_indices"]]
    assert episodes == list(range(40)) and len(recs) == 5


def test_killed_clustering_actor_comes_back_with_the_same_bank(ray_local, tmp_path):
    import ray

    trainer = Trainer(_ray_cfg(tmp_path, "runtime.total_env_steps=4000"), log=lambda *_: None)
    trainer.start_policy(0)
    for _ in range(3):
        trainer.step()
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
    assert new_pid != old_pid
    assert after["policies"] == before["policies"] and after["assignments"] == before["assignments"] == 3
    trainer.step()
    recs = trainer.backend.call_clustering("assignments", 0, 100)
    trainer.close()
    assert [e for r in recs for e in r["episode_indices"]] == list(range(32))
