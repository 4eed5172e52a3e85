"""Learners that survive: a restarted learner comes back with the policy's newest weights,
optimizer state and version, and a retried update is applied exactly once."""

import math
import os
import signal
import time

import pytest
import torch

from covers_dist.runtime.driver import Trainer
from covers_dist.runtime.learner import PolicyLearner, live_state_key
from covers_dist.runtime.processes import list_processes
from covers_dist.runtime.rollout import EpisodeSpec, RolloutWorker

from test_runtime_serial import assignments, learner_weights, same_weights, tiny_cfg


@pytest.fixture(scope="module")
def batches(tmp_path_factory):
    """Two real batches of episodes (a rollout worker with policy 0's initial weights)."""
    cfg = tiny_cfg(tmp_path_factory.mktemp("eps"))
    weights = PolicyLearner(cfg, 0).weights()[1]
    worker = RolloutWorker(cfg, 0)
    out = [worker.sample([EpisodeSpec(i, "reach", "e", 0) for i in range(b * 4, b * 4 + 4)], 0, 1, weights) for b in (0, 1)]
    worker.close()
    return cfg, out


def _equal(a, b):
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_restarted_learner_resumes_its_state_and_applies_a_retried_update_once(batches, tmp_path):
    cfg, (first, second) = batches
    reference = PolicyLearner(cfg, 0)  # never restarted
    ref1 = reference.update(first, 0)
    ref2 = reference.update(second, 1)

    crashed = PolicyLearner(cfg, 0, storage=str(tmp_path))
    got1 = crashed.update(first, 0)
    assert (tmp_path / live_state_key(0)).is_file()
    del crashed  # the process dies after the update, before the caller saw its result

    restarted = PolicyLearner(cfg, 0, storage=str(tmp_path))  # what Ray does: the constructor again
    assert restarted.restored and restarted.version == 1
    retried = restarted.update(first, 0)  # the caller retries the same call
    assert restarted.version == 1 and retried[1] == got1[1] == ref1[1] == 1
    assert retried[0] == got1[0]  # the stored result: not applied a second time
    _equal(retried[2], ref1[2])
    got2 = restarted.update(second, 1)
    assert got2[1] == 2
    _equal(got2[2], ref2[2])  # weights, Adam moments and the shuffling RNG all came back
    # the pipelined loop's previous result is kept too (lost weights are re-created by re-execution)
    _equal(restarted.update(first, 0)[2], ref1[2])
    with pytest.raises(RuntimeError, match="version 2 but an update from version 5"):
        restarted.update(first, 5)


class _Died(BaseException):
    """The learner's process dying: nothing after this point runs (not an ``Exception`` either)."""


#: statistics that measure time, not the update
_TIMING = {"update_time_s", "samples_per_s"}


def _same_stats(a, b):
    assert a.keys() == b.keys()
    for k in a.keys() - _TIMING:
        x, y = a[k], b[k]
        assert x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y)), (k, x, y)


def _same_state(a, b, where="state"):
    """Two nested learner states (tensors, numbers, dicts, lists) hold the same values."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            _same_state(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same_state(x, y, f"{where}[{i}]")
    else:
        assert a == b, (where, a, b)


@pytest.mark.parametrize(
    "lost_update, crash",
    [(1, "before the save"), (2, "before the save"), (2, "while saving")],
)
def test_learner_killed_between_its_update_and_its_live_save_recovers(batches, tmp_path, lost_update, crash):
    """The process dies after the real update changed the learner in memory and before its live
    state is on disk (before the save starts, or mid-save, leaving a partial temporary file). The
    live file still holds the state before that update, so Ray's restarted actor comes back one
    version behind; the retried call (same episodes, same ``base_version``) then applies the update
    again from exactly that state and gives what the lost update gave, and what a learner that
    never crashed gives, down to the optimizer state; later updates go on as in the clean run."""
    cfg, (first, second) = batches
    data = (first, second)
    reference = PolicyLearner(cfg, 0)  # never crashes
    ref, ref_states = [], []
    for v, episodes in enumerate(data):
        ref.append(reference.update(episodes, v))
        ref_states.append(reference.ppo.state_dict())

    live = tmp_path / live_state_key(0)
    learner = PolicyLearner(cfg, 0, storage=str(tmp_path))
    for v in range(lost_update - 1):
        learner.update(data[v], v)

    def die() -> None:
        if crash == "while saving":
            live.parent.mkdir(parents=True, exist_ok=True)
            (live.parent / f".{live.name}.{os.getpid()}.tmp").write_bytes(b"half a torch file")
        raise _Died

    learner._save_live = die
    base = lost_update - 1
    with pytest.raises(_Died):
        learner.update(data[base], base)
    assert learner.version == lost_update  # the update happened, in memory only
    lost_stats, lost_weights = learner.results[lost_update]
    del learner

    if lost_update == 1:
        assert not live.is_file()  # nothing was saved yet: the restart is a fresh learner
    else:
        assert torch.load(live, weights_only=False)["version"] == base
    restarted = PolicyLearner(cfg, 0, storage=str(tmp_path))  # what Ray does: the constructor again
    assert restarted.restored == (lost_update > 1) and restarted.version == base
    stats, version, weights = restarted.update(data[base], base)  # the caller retries the same call
    assert version == lost_update == ref[base][1]
    _equal(weights, lost_weights)
    _equal(weights, ref[base][2])
    _same_stats(stats, lost_stats)
    _same_stats(stats, ref[base][0])
    _same_state(restarted.ppo.state_dict(), ref_states[base])  # weights, Adam moments, counters, RNG
    assert torch.load(live, weights_only=False)["version"] == lost_update  # the live file is current again
    # the rest of the run is the clean run's
    for v in range(lost_update, len(data)):
        stats, version, weights = restarted.update(data[v], v)
        assert version == ref[v][1]
        _equal(weights, ref[v][2])
        _same_stats(stats, ref[v][0])
    _same_state(restarted.ppo.state_dict(), ref_states[-1])
    again = PolicyLearner(cfg, 0, storage=str(tmp_path))  # a later restart finds the newest state
    assert again.version == len(data)
    _same_state(again.ppo.state_dict(), ref_states[-1])


def test_unreadable_live_state_is_a_clear_error(batches, tmp_path):
    cfg, (first, _) = batches
    PolicyLearner(cfg, 0, storage=str(tmp_path)).update(first, 0)
    (tmp_path / live_state_key(0)).write_bytes(b"not a torch file")
    with pytest.raises(RuntimeError, match="(unreadable|refused).*--resume"):
        PolicyLearner(cfg, 0, storage=str(tmp_path))


def test_checkpoint_state_becomes_the_live_state(batches, tmp_path):
    cfg, (first, second) = batches
    learner = PolicyLearner(cfg, 0, storage=str(tmp_path))
    learner.update(first, 0)
    saved = learner.state_dict()
    learner.update(second, 1)
    learner.load_state_dict(saved)  # a resume from a checkpoint older than the live state
    assert PolicyLearner(cfg, 0, storage=str(tmp_path)).version == 1


def _wait_for_new_pid(run_dir, role, old_pid, timeout_s=90):
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        for p in list_processes(run_dir):
            if p["role"] == role and p["pid"] != old_pid:
                return p["pid"]
        time.sleep(0.2)
    raise AssertionError(f"no restarted {role} within {timeout_s} s")


@pytest.mark.slow
@pytest.mark.parametrize("per_process", [1, 8])
def test_learner_killed_during_updates_ends_where_the_clean_run_ends(ray_local, tiny_serial_run, tmp_path, per_process):
    """Two SIGKILLs of a learner actor mid-update on Ray; the run ends with the serial run's
    assignments and weights, one version per update. With ``runtime.learners_per_process=8`` the
    killed process hosts every policy's learner, and each comes back from its own live state. Slow
    tier: in the default suite the chaos test kills a learner (and every other kind) and compares
    with the clean run, and the tests above cover each point of a learner's death deterministically,
    in process."""
    serial = tiny_serial_run[:2]  # the clean run: the same config and 1600 env steps, serial
    cfg = tiny_cfg(tmp_path / "r", "runtime.total_env_steps=1600", "runtime.serial=false",
                   f"runtime.learners_per_process={per_process}")  # fmt: skip
    trainer = Trainer(cfg, log=lambda *_: None)
    trainer.start_policy(0)
    kills = 0
    while trainer.env_steps < cfg.runtime.total_env_steps:
        trainer.step()  # leaves this iteration's update running on its learner
        if trainer.iteration in (1, 3):
            (learner,) = [p for p in list_processes(tmp_path / "r") if p["role"] == "learner" and p["index"] == 0]
            os.kill(learner["pid"], signal.SIGKILL)  # mid-update (or just after it: both must hold)
            kills += 1
            _wait_for_new_pid(tmp_path / "r", "learner", learner["pid"])
    trainer.drain()
    got = assignments(trainer), learner_weights(trainer)
    versions = {pid: trainer.backend.call_learner(pid, "weights")[0] for pid in sorted(trainer.weights.versions)}
    trainer.close()
    assert kills == 2
    assert got[0] == serial[0]
    same_weights(got[1], serial[1])
    assert versions[0] == sum(1 for pid, _ in serial[0] if pid == 0)  # one version per update: none doubled
