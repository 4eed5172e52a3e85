"""The COVERS loop in one process: phases, checkpoints, resume, determinism."""

import json
import os
import shutil
import signal

import numpy as np
import pytest
import torch

from covers_dist.config import load_config
from covers_dist.runtime.checkpoint import CheckpointError, latest_valid_checkpoint, list_checkpoints, verify_checkpoint
from covers_dist.runtime.driver import Trainer

TINY = [
    "runtime.serial=true",
    "runtime.num_workers=2",
    "runtime.envs_per_worker=4",
    "env.episodes_per_task=8",
    "env.max_episode_steps=50",
    "clustering.update_every=8",
    "ppo.epochs=1",
    "ppo.minibatch_size=200",
    "network.channels=[2,4]",  # narrow: the loop's tests do not depend on the network's width
    "network.hidden=8",
    "runtime.log_every_s=1000",
    "runtime.learner_ahead=false",  # on Ray: no learner started for a policy the short runs never create
]


def tiny_cfg(tmp_path, *extra):
    return load_config("configs/smoke.yaml", [*TINY, f"runtime.run_dir={tmp_path}", *extra])


def assignments(trainer):
    return [(r["policy_id"], r["decision"]) for r in trainer.backend.call_clustering("assignments", 0, 1000)]


def learner_weights(trainer):
    """{policy id: its learner's newest weights}, every policy of the trainer's bank."""
    return {pid: trainer.backend.call_learner(pid, "weights")[1] for pid in sorted(trainer.weights.versions)}


def same_weights(a, b):
    """Two {policy id: weights} maps (learner_weights) name the same policies, bit for bit equal."""
    assert a.keys() == b.keys()
    for pid in a:
        for name in a[pid]:
            assert torch.equal(a[pid][name], b[pid][name]), (pid, name)


def test_serial_loop_runs_phases_and_writes_metrics(tiny_serial_run):
    *_, tmp_path = tiny_serial_run  # 1600 env steps of the tiny config (conftest.py), finished
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4]
    assert rows[-1]["env_steps"] == 1600
    for phase in ("sample", "assign", "update_submit", "update_wait", "record"):
        assert rows[-1][f"time/{phase}"] > 0
    episodes = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert [e["episode_index"] for e in episodes] == list(range(32))
    assert (tmp_path / "tb").is_dir()
    verify_checkpoint(list_checkpoints(tmp_path)[-1])


def test_same_seed_same_assignments_and_losses(tiny_serial_run, tmp_path):
    """A second run of the same config and seed (the first: conftest.py's, made earlier in this process)."""
    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=1600")
    trainer = Trainer(cfg, log=lambda *_: None)
    trainer.run()
    trainer.close()
    runs = []
    for recorded, run_dir in ((tiny_serial_run[0], tiny_serial_run[2]), (assignments(trainer), tmp_path)):
        rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
        runs.append((recorded, [r.get("ppo/policy_loss") for r in rows], [r["return/" + t] for r in rows for t in ["reach", "push", "avoid"] if "return/" + t in r]))
    assert len(runs[0][1]) == 4 and runs[0] == runs[1]


def test_sigterm_checkpoints_after_the_iteration_and_the_resumed_run_ends_as_the_unbroken_one(tiny_serial_run, tmp_path):
    """SIGTERM in the middle of a run, in this process (the signal sent from the loop's own iteration
    hook): the run stops after that iteration, checkpoints it, and a resume ends exactly where the
    unbroken run of conftest.py ends. The same as a user's `covers-dist train` process:
    tests/test_train_cli.py (start-up; the whole CLI round trip is in the slow tier)."""
    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=1600", "runtime.checkpoint_every=100")
    logs = []
    first = Trainer(cfg, log=logs.append)
    first.on_iteration.append(lambda: first.iteration == 2 and os.kill(os.getpid(), signal.SIGTERM))
    result = first.run()
    first.close()
    assert result["status"] == "interrupted" and first.iteration == 2
    assert any(line.startswith("received signal") for line in logs)
    assert [c.name for c in list_checkpoints(tmp_path)] == ["ckpt-000002"]
    second = Trainer(cfg, resume=True, log=lambda *_: None)
    assert second.run()["status"] == "finished"
    weights = learner_weights(second)
    second.close()
    same_weights(weights, tiny_serial_run[1])
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4]
    episodes = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert [e["episode_index"] for e in episodes] == list(range(32))
    unbroken = [json.loads(line) for line in (tiny_serial_run[2] / "metrics.jsonl").read_text().splitlines()]
    assert assignments(second) == tiny_serial_run[0]
    assert [r.get("ppo/policy_loss") for r in rows] == [r.get("ppo/policy_loss") for r in unbroken]
    from covers_dist.bench.chaos import differences, stable

    assert differences(stable(rows), stable(unbroken)) == []  # every row whole, but its wall-clock fields


def _tree(root):
    """{relative path: bytes} of every file under ``root``."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_resume_continues_in_the_directory_given_and_leaves_the_original_alone(tiny_serial_run, tmp_path):
    """A run stopped after 2 of 4 iterations is copied elsewhere (its local storage inside it) and the
    copy resumed by `train --resume COPY`: the copy ends where the unbroken run ends, its saved config
    names the copy, and not one byte of the original changes."""
    from covers_dist.runtime.driver import train

    original = tmp_path / "original"
    cfg = tiny_cfg(original, "runtime.total_env_steps=1600", "runtime.checkpoint_every=100",
                   f"runtime.storage={original / 'store'}")  # fmt: skip
    first = Trainer(cfg, log=lambda *_: None)
    first.on_iteration.append(lambda: first.iteration == 2 and os.kill(os.getpid(), signal.SIGTERM))
    assert first.run()["status"] == "interrupted"
    first.close()
    copy = tmp_path / "moved" / "copy"
    shutil.copytree(original, copy)
    before = _tree(original)
    logs = []
    assert train(resume_dir=str(copy), log=logs.append)["status"] == "finished"
    assert _tree(original) == before
    saved = load_config(copy / "config.yaml")
    assert saved.runtime.run_dir == str(copy) and saved.runtime.storage == str(copy / "store")
    rows = [json.loads(line) for line in (copy / "metrics.jsonl").read_text().splitlines()]
    unbroken = [json.loads(line) for line in (tiny_serial_run[2] / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4]
    assert [r.get("ppo/policy_loss") for r in rows] == [r.get("ppo/policy_loss") for r in unbroken]
    assert [c.name for c in list_checkpoints(copy)][-1] == "ckpt-000004"
    assert any(str(copy) in line for line in logs)


def test_resume_continues_with_the_same_bank_and_counters(tmp_path):
    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=800", "runtime.checkpoint_every=100")
    first = Trainer(cfg, log=lambda *_: None)
    first.run()
    bank_before = assignments(first)
    first.close()
    cfg2 = tiny_cfg(tmp_path, "runtime.total_env_steps=1600", "runtime.checkpoint_every=100")
    second = Trainer(cfg2, resume=True, log=lambda *_: None)
    assert second.iteration == 0  # restored on run()
    second.run()
    assert second.iteration == 4 and second.next_episode == 32 and second.env_steps == 1600
    after = assignments(second)
    assert after[: len(bank_before)] == bank_before and len(after) == 4
    second.close()


def test_corrupt_newest_checkpoint_falls_back_to_previous(tmp_path):
    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=1200", "runtime.checkpoint_every=1")
    t = Trainer(cfg, log=lambda *_: None)
    t.run()
    t.close()
    ckpts = list_checkpoints(tmp_path)
    assert len(ckpts) >= 2
    newest = ckpts[-1]
    (newest / "driver.json").write_text("{garbage")
    with pytest.raises(CheckpointError, match="driver.json is corrupt"):
        verify_checkpoint(newest)
    messages = []
    assert latest_valid_checkpoint(tmp_path, log=messages.append) == ckpts[-2]
    assert "falling back to the previous checkpoint" in messages[0]
    shutil.rmtree(ckpts[-2] / "learners")
    assert latest_valid_checkpoint(tmp_path, log=messages.append) == ckpts[-3]


def test_resume_without_checkpoint_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no valid checkpoint"):
        Trainer(tiny_cfg(tmp_path), resume=True)


def test_resume_after_a_kill_past_the_last_checkpoint_logs_each_iteration_once(tmp_path):
    """A run killed after its last checkpoint redoes the later iterations: their rows are not doubled."""
    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=1600", "runtime.checkpoint_every=3")
    trainer = Trainer(cfg, log=lambda *_: None)
    trainer.run()
    trainer.close()
    shutil.rmtree(list_checkpoints(tmp_path)[-1])  # as if killed (SIGKILL) before the final checkpoint
    resumed = Trainer(cfg, resume=True, log=lambda *_: None)
    resumed.run()
    resumed.close()
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4]
    episodes = [json.loads(line)["episode_index"] for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert episodes == list(range(32))


def test_checkpoints_record_the_network_probe_and_loading_checks_it(tmp_path):
    from covers_dist.runtime.saved_run import load_saved_run, probe_mismatch

    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=800")
    trainer = Trainer(cfg, log=lambda *_: None)
    trainer.run()
    probe = trainer.backend.network_probe()
    trainer.close()
    saved = json.loads((latest_valid_checkpoint(tmp_path) / "driver.json").read_text())["network_probe"]
    np.testing.assert_array_equal(saved, probe)
    lines = []
    load_saved_run(tmp_path, log=lines.append)
    assert not [line for line in lines if "warning" in line]
    assert probe_mismatch(saved, probe, cfg) is None
    assert "builds the network differently" in probe_mismatch(list(np.asarray(saved) * 1.5), probe, cfg)
    assert probe_mismatch(None, probe, cfg) is None  # an old checkpoint of a net without the stem
    stem = load_config("configs/quickstart.yaml")
    assert "drawn per process" in probe_mismatch(None, probe, stem)


def test_learner_threads_default_to_one_unless_the_learner_reserves_cores():
    """``runtime.learner_threads: 0`` (auto): 1 thread beside the rollout workers, the reserved cores
    where ``runtime.learner_num_cpus`` gives it some; an explicit count is kept; a negative one is a
    config error."""
    from covers_dist.config import ConfigError
    from covers_dist.runtime.learner import learner_threads

    def threads(*sets):
        return learner_threads(load_config("configs/smoke.yaml", list(sets)))

    assert threads() == 1
    assert threads("runtime.learner_num_cpus=2.5") == 3
    assert threads("runtime.learner_threads=2") == 2
    assert threads("runtime.learner_threads=2", "runtime.learner_num_cpus=8") == 2
    with pytest.raises(ConfigError, match="learner_threads"):
        threads("runtime.learner_threads=-1")


def test_log_std_cap_reaches_the_published_weights(tmp_path):
    """ppo.log_std_cap in a run: the metrics name each update's cap (falling to the final value at
    the run's length in updates) and the weights the workers act with carry the clipped std."""
    cfg = tiny_cfg(tmp_path, "runtime.total_env_steps=1600", "ppo.log_std_cap=-2.0", "env.tasks=[reach]")
    trainer = Trainer(cfg, log=lambda *_: None)
    try:
        trainer.run()
        rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
        caps = [r["ppo/log_std_cap"] for r in rows if "ppo/log_std_cap" in r]
        start = cfg.network.init_log_std
        # rows report updates 1, 2, ... (the last row's update may still be in flight at its row)
        assert len(caps) >= 3 and caps == pytest.approx([start + (-2.0 - start) * k / 4 for k in range(1, len(caps) + 1)])
        (pid,) = trainer.weights.versions  # one task: one policy, 4 updates, so the cap is at its final value
        assert float(trainer.backend.call_learner(pid, "weights")[1]["log_std_free"].max()) <= -2.0 + 1e-7
    finally:
        trainer.close()
