"""``bench scale``: the time model's projection, and the loop on a local 2-node Ray cluster."""

import json

import pytest

from covers_dist.bench.scale import project
from covers_dist.cli import main


def test_projection_follows_the_time_model():
    measured = {"sample_steps_per_s": 400.0, "workers": 2, "phase_assign_s": 0.1, "phase_record_s": 0.1}
    # 800 steps per iteration, 16 workers at 200 steps/s each: 0.25 s of sampling
    p = project(measured, 800, 16, update_samples_per_s=3200.0, epochs=2)  # 0.5 s of updating
    assert p["per_worker_steps_per_s"] == 200.0 and p["sample_s"] == 0.25 and p["update_s"] == 0.5
    assert p["sequential_steps_per_s"] == round(800 / (0.25 + 0.5 + 0.2), 1)
    assert p["pipelined_steps_per_s"] == round(800 / (0.5 + 0.2), 1)
    assert p["bound"] == "update"
    fast_learner = project(measured, 800, 16, update_samples_per_s=64000.0, epochs=2)
    assert fast_learner["bound"] == "sampling"


@pytest.mark.bench
def test_bench_scale_runs_on_a_loopback_two_node_cluster(capsys):
    argv = ["bench", "scale", "--config", "configs/smoke.yaml", "--nodes", "2", "--iterations", "1", "--warmup", "0",
            "--set", "env.max_episode_steps=20", "--set", "clustering.update_every=4", "--set", "ppo.minibatch_size=40",
            "--set", "runtime.envs_per_worker=2", "--json"]  # fmt: skip
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("1n_sequential", "1n_pipelined", "2n_sequential", "2n_pipelined"):
        assert out[key]["env_steps_per_s"] > 0 and out[key]["env_steps"] == 80
    assert out["sampling_scaling"] > 0 and out["projection"]["workers"] == 16
