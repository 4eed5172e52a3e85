"""A run on a cluster: refused up front when its learners can never be placed, when its run directory
would die with the job, and its clustering actor in a namespace of its own; a retried job continues."""

import json

import pytest

from covers_dist.config import ConfigError, load_config
from covers_dist.runtime.actors import run_namespace
from covers_dist.runtime.placement import ClusterTooSmall, check_fits, learners_needed
from covers_dist.runtime.ray_setup import check_run_dir_outlives_the_job

PAPER = "configs/covers_metaworld.yaml"
# the manifest's cluster (deploy/rayjob.yaml): a CPU-less head, rollout nodes, one GPU node
CLUSTER = [{"CPU": 0.0}, *[{"CPU": 4.0}] * 4, {"CPU": 4.0, "GPU": 1.0}]


def test_the_paper_config_fits_the_manifests_cluster_and_a_whole_gpu_per_learner_does_not():
    cfg = load_config(PAPER)
    assert learners_needed(cfg) == len(cfg.env.tasks) + 1 == 5  # four groups and the learner started ahead
    check_fits(cfg, CLUSTER)  # 0.2 GPU per learner: five share the one GPU
    whole = load_config(PAPER, ["runtime.num_gpus=1"])
    with pytest.raises(ClusterTooSmall, match=r"needs 5 learner processes.*1 GPU.*set runtime.num_gpus to 0.2 or less"):
        check_fits(whole, CLUSTER)
    shared = load_config(PAPER, ["runtime.num_gpus=1", "runtime.learners_per_process=5"])
    assert learners_needed(shared) == 1
    check_fits(shared, CLUSTER)  # the five learners in one process: that process takes the one GPU
    halves = load_config(PAPER, ["runtime.num_gpus=1", "runtime.learners_per_process=3"])
    assert learners_needed(halves) == 2  # policies 0-2 and 3-4
    with pytest.raises(ClusterTooSmall, match=r"needs 2 learner processes.*3 policies per learner process"):
        check_fits(halves, CLUSTER)
    check_fits(whole, [*CLUSTER, {"CPU": 4, "GPU": 4}])  # or more GPUs
    single = load_config(PAPER, ["runtime.num_gpus=1", "runtime.method=equi"])
    assert learners_needed(single) == 1
    check_fits(single, CLUSTER)  # one policy for the whole stream: one learner, one GPU
    with pytest.raises(ClusterTooSmall, match=r"has 0 GPUs.*runtime.num_gpus: 0"):
        check_fits(cfg, [{"CPU": 64.0}])
    assert issubclass(ClusterTooSmall, ConfigError)  # the CLI reports it as a config error (exit 2)


def test_workers_and_learner_cpus_count_against_the_nodes():
    cfg = load_config("configs/smoke.yaml", ["runtime.num_workers=3"])
    with pytest.raises(ClusterTooSmall, match="3 rollout workers"):
        check_fits(cfg, [{"CPU": 2.0}])
    cfg = load_config("configs/smoke.yaml", ["runtime.learner_num_cpus=1", "runtime.learner_ahead=false"])
    check_fits(cfg, [{"CPU": 5.0}])  # 2 workers + 3 learners
    with pytest.raises(ClusterTooSmall, match="learner_num_cpus"):
        check_fits(cfg, [{"CPU": 4.0}])
    check_fits(load_config("configs/smoke.yaml"), [{"CPU": 2.0}])  # CPU learners that reserve nothing


def test_a_real_ray_cluster_without_gpus_refuses_gpu_learners_before_any_actor_starts(ray_local, tmp_path, capsys):
    from covers_dist.cli import main

    code = main(["train", "--config", "configs/smoke.yaml", "--run-dir", str(tmp_path / "run"),
                 "--set", "runtime.num_gpus=0.5"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "config error" in err and "has 0 GPUs" in err, err
    assert not (tmp_path / "run" / "checkpoints").exists()
    import ray

    assert not [a for a in ray.util.list_named_actors(all_namespaces=True) if a["name"] == "covers-clustering-smoke"]


def test_a_relative_run_dir_is_refused_inside_a_ray_job_with_a_working_dir(monkeypatch, tmp_path):
    job = {"runtime_env": {"working_dir": "gcs://_ray_pkg_0123.zip"}, "metadata": {}}
    monkeypatch.setenv("RAY_JOB_CONFIG_JSON_ENV_VAR", json.dumps(job))
    with pytest.raises(ConfigError, match=r"relative.*deletes when the job ends.*absolute"):
        check_run_dir_outlives_the_job("runs/smoke")
    check_run_dir_outlives_the_job(str(tmp_path / "runs" / "smoke"))  # absolute: fine
    monkeypatch.setenv("RAY_JOB_CONFIG_JSON_ENV_VAR", json.dumps({"runtime_env": {}}))
    check_run_dir_outlives_the_job("runs/smoke")  # a job without a working dir runs where it was started
    monkeypatch.delenv("RAY_JOB_CONFIG_JSON_ENV_VAR")
    check_run_dir_outlives_the_job("runs/smoke")  # not a Ray job


def test_each_run_directory_has_its_own_clustering_namespace(tmp_path):
    a = load_config("configs/smoke.yaml", [f"runtime.run_dir={tmp_path / 'a'}"])
    b = load_config("configs/smoke.yaml", [f"runtime.run_dir={tmp_path / 'b'}"])
    again = load_config("configs/smoke.yaml", [f"runtime.run_dir={tmp_path / 'x' / '..' / 'a'}"])
    assert run_namespace(a) != run_namespace(b)
    assert run_namespace(a) == run_namespace(again) and run_namespace(a).startswith("covers-dist-")


def test_resume_existing_starts_a_new_run_and_continues_an_existing_one(tmp_path, capsys, one_torch_thread):
    from covers_dist.cli import main

    run = tmp_path / "run"
    args = ["train", "--config", "configs/smoke.yaml", "--serial", "--run-dir", str(run),
            "--set", "runtime.total_env_steps=400", "--set", "clustering.update_every=8", "--set", "env.episodes_per_task=8",
            "--set", "network.channels=[2,4]", "--set", "network.hidden=8", "--set", "env.image_size=16",
            "--set", "env.max_episode_steps=25"]  # fmt: skip
    assert main([*args, "--resume-existing"]) == 0  # nothing there yet: a new run
    first = capsys.readouterr().out
    assert "continuing" not in first and '"status": "finished"' in first
    assert main(args) == 2 and "already holds a run" in capsys.readouterr().err  # without the flag: refused
    assert main([*args, "--resume-existing"]) == 0  # a retried job: the run goes on from its checkpoint
    again = capsys.readouterr().out
    assert "holds a run: continuing it" in again and '"status": "finished"' in again
    with pytest.raises(SystemExit, match="contradict"):
        main([*args, "--resume-existing", "--overwrite"])
