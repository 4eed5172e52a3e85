"""clustering.assign_at: assignment from the first frames before acting (reset) vs after (iteration)."""

import json

import numpy as np
import pytest

from covers_dist.config import ConfigError, load_config
from covers_dist.runtime.backends import RayBackend, SerialBackend
from covers_dist.runtime.driver import Trainer
from covers_dist.runtime.rollout import EpisodeSpec

TINY = [
    "runtime.serial=true",
    "runtime.num_workers=2",
    "runtime.envs_per_worker=4",
    "env.episodes_per_task=6",  # a task switch inside most batches of 4
    "env.max_episode_steps=10",
    "clustering.update_every=4",
    "clustering.feature_source=own",  # the tiny untrained nets split the toy tasks on their own features
    "ppo.epochs=1",
    "ppo.minibatch_size=40",
    "network.channels=[2,4]",
    "network.hidden=8",
    "runtime.log_every_s=1000",
    "runtime.total_env_steps=480",
    "runtime.checkpoint_every=100",
]


def _run(tmp_path, mode):
    overrides = [*TINY, f"runtime.run_dir={tmp_path / mode}", f"clustering.assign_at={mode}"]
    cfg = load_config("configs/smoke.yaml", overrides)
    trainer = Trainer(cfg, log=lambda _m: None)
    try:
        result = trainer.run()
    finally:
        trainer.close()
    episodes = [json.loads(line) for line in (tmp_path / mode / "episodes.jsonl").read_text().splitlines()]
    return result, episodes


def test_reset_mode_acts_every_episode_with_its_assigned_policy(tmp_path, one_torch_thread):
    late, late_eps = _run(tmp_path, "iteration")
    early, early_eps = _run(tmp_path, "reset")
    assert len(late_eps) == len(early_eps) == 48
    acted_other = [e["policy_id"] != e["assigned_policy"] for e in late_eps]
    # the paper's order: the episodes after a task switch are acted by the previous group's policy
    assert sum(acted_other) > 0
    assert late["row"]["wrong_policy_fraction"] == pytest.approx(np.mean(acted_other))
    assert all(e["policy_id"] == e["assigned_policy"] for e in early_eps)
    assert early["row"]["wrong_policy_fraction"] == 0.0


def test_first_frames_are_the_frames_the_episodes_start_from(tmp_path, one_torch_thread):
    cfg = load_config("configs/smoke.yaml", [*TINY, f"runtime.run_dir={tmp_path}"])
    backend = SerialBackend(cfg, tmp_path)
    try:
        tasks = [("reach", "r", 0), ("push", "f", 1), ("avoid", "e", 2), ("reach", "r3f", 0)]
        specs = [EpisodeSpec(i, t, g, j) for i, (t, g, j) in enumerate(tasks)]
        plan = [specs[0::2], specs[1::2]]
        frames = backend.first_frames(plan)
        from covers_dist.runtime.learner import PolicyLearner

        weights = PolicyLearner(cfg, 0).model.get_weights()
        firsts, summaries, _ = backend.sample(plan, 0, 1, weights)
        order = np.argsort([s["episode_index"] for s in summaries])
        np.testing.assert_array_equal(frames["image"], np.concatenate([firsts[i]["image"] for i in order]))
        np.testing.assert_array_equal(frames["proprio"], np.concatenate([firsts[i]["proprio"] for i in order]))
    finally:
        backend.shutdown()


def test_ray_first_frames_match_serial(tmp_path, ray_local, one_torch_thread):
    cfg = load_config("configs/smoke.yaml", [*TINY, "runtime.serial=false", f"runtime.run_dir={tmp_path}"])
    specs = [EpisodeSpec(i, "push", g, 1) for i, g in enumerate(["e", "r", "r2f", "f"])]
    plan = [specs[:2], specs[2:]]
    serial = SerialBackend(cfg, tmp_path / "serial")
    remote = RayBackend(cfg, tmp_path / "ray")
    try:
        a, b = serial.first_frames(plan), remote.first_frames(plan)
        for key in ("image", "proprio"):
            np.testing.assert_array_equal(a[key], b[key])
    finally:
        serial.shutdown()
        remote.shutdown()


def test_reset_needs_one_initial_frame():
    with pytest.raises(ConfigError, match="assign_at=reset needs clustering.initial_frames=1"):
        load_config("configs/smoke.yaml", ["clustering.assign_at=reset", "clustering.initial_frames=2"])
    with pytest.raises(ConfigError, match="clustering.assign_at"):
        load_config("configs/smoke.yaml", ["clustering.assign_at=never"])
