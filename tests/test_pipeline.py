"""The pipelined loop (runtime.pipeline): sampling overlaps the previous update, exactly
reproducible, resumable mid-pipeline, and equal on Ray and in one process."""

import json

import pytest

from covers_dist.runtime.driver import Trainer

from test_runtime_serial import assignments, learner_weights, same_weights, tiny_cfg


def _run(cfg, resume=False):
    trainer = Trainer(cfg, resume=resume, log=lambda *_: None)
    trainer.run()
    if not cfg.runtime.learner_ahead:  # the tiny config: every learner started when its policy appeared
        assert trainer.backend.spare_learners() == []
    result = (assignments(trainer), learner_weights(trainer))
    trainer.close()
    return result


def _rows(run_dir, name="metrics.jsonl"):
    return [json.loads(line) for line in (run_dir / name).read_text().splitlines()]


def _losses(run_dir):
    return [r.get("ppo/policy_loss") for r in _rows(run_dir)]


def _batches(run_dir):
    """Per metrics row: (its iteration, the iteration and policy of the batch its update trained on)."""
    return [(r["iteration"], r.get("ppo/batch_iteration"), r.get("ppo/batch_policy")) for r in _rows(run_dir)]


def _policy_per_iteration(run_dir):
    acted = {}
    for e in _rows(run_dir, "episodes.jsonl"):
        acted.setdefault(e["iteration"], set()).add(e["assigned_policy"])
    assert all(len(p) == 1 for p in acted.values())  # one policy trains on an iteration's batch
    return {it: p.pop() for it, p in acted.items()}


def test_pipelined_rows_report_the_previous_update_and_differ_from_sequential(tiny_serial_run, tmp_path):
    _, _, piped_dir = tiny_serial_run  # 1600 env steps, runtime.pipeline=true (the default)
    _run(tiny_cfg(tmp_path / "s", "runtime.total_env_steps=1600", "runtime.pipeline=false"))
    piped, seq = _losses(piped_dir), _losses(tmp_path / "s")
    assert piped[0] is None and all(v is not None for v in piped[1:])  # nothing finished yet in iteration 1
    assert all(v is not None for v in seq)
    # the first update is the same computation (same data, same weights); later ones see lagged samples
    assert piped[1] == seq[0]
    assert piped[2:] != seq[1:-1]
    # each row names the batch whose update it reports: the previous iteration's when pipelined
    for run_dir, lag in ((piped_dir, 1), (tmp_path / "s", 0)):
        policies = _policy_per_iteration(run_dir)
        rows = [b for b in _batches(run_dir) if b[1] is not None]
        assert [it - lag for it, _, _ in rows] == [batch for _, batch, _ in rows]
        assert [policies[batch] for _, batch, _ in rows] == [pid for _, _, pid in rows]


def test_pipelined_run_resumed_from_a_checkpoint_with_an_update_in_flight_equals_the_uninterrupted_run(tmp_path):
    full = _run(tiny_cfg(tmp_path / "full", "runtime.total_env_steps=2000", "runtime.checkpoint_every=100"))
    _run(tiny_cfg(tmp_path / "cut", "runtime.total_env_steps=800", "runtime.checkpoint_every=100"))
    state = json.loads(sorted((tmp_path / "cut" / "checkpoints").iterdir())[-1].joinpath("driver.json").read_text())
    assert state["pending_update"]["policy_id"] in state["policies"]  # the checkpoint held an update in flight
    resumed = _run(tiny_cfg(tmp_path / "cut", "runtime.total_env_steps=2000", "runtime.checkpoint_every=100"), True)
    assert resumed[0] == full[0]
    same_weights(resumed[1], full[1])
    assert _losses(tmp_path / "cut")[2:] == _losses(tmp_path / "full")[2:]
    assert _batches(tmp_path / "cut")[2:] == _batches(tmp_path / "full")[2:]  # the restored update names its batch


@pytest.mark.slow
def test_ray_pipelined_run_equals_the_serial_pipelined_run(ray_local, tiny_serial_run, tmp_path):
    """Without faults. The default suite's chaos test (``tests/test_chaos.py``) compares a Ray run
    of two rollout workers, pipelined, with its serial run too, with every kind of process killed
    once on the way."""
    serial = tiny_serial_run[:2]  # the same config, 1600 env steps, in this process
    distributed = _run(tiny_cfg(tmp_path / "r", "runtime.total_env_steps=1600", "runtime.serial=false"))
    assert distributed[0] == serial[0]
    same_weights(distributed[1], serial[1])


@pytest.mark.slow
def test_policies_sharing_one_learner_process_train_as_with_a_process_each(ray_local, tiny_serial_run, tmp_path):
    """runtime.learners_per_process: every policy's learner in one Ray process (the one started ahead
    too); the run ends with the serial run's assignments and weights, and one learner process was
    recorded where the default starts one per policy. Slow tier (half a minute beside the other
    worker): the default suite's chaos test runs its two policies' learners in one process, kills
    it, and must still end equal to the serial run."""
    from covers_dist.runtime.processes import list_processes

    serial = tiny_serial_run[:2]
    assert len(serial[1]) >= 2  # the tiny stream makes more than one policy: the process is shared
    cfg = tiny_cfg(tmp_path / "r", "runtime.total_env_steps=1600", "runtime.serial=false",
                   "runtime.learners_per_process=8", "runtime.learner_ahead=true")  # fmt: skip
    trainer = Trainer(cfg, log=lambda *_: None)
    trainer.run()
    assert trainer.backend.learner_processes() == 1
    assert trainer.backend.spare_learners() == [max(trainer.weights.versions) + 1]
    shared = (assignments(trainer), learner_weights(trainer))
    trainer.close()
    assert shared[0] == serial[0]
    same_weights(shared[1], serial[1])
    learners = [p for p in list_processes(tmp_path / "r") if p["role"] == "learner"]
    assert [p["index"] for p in learners] == [0]
