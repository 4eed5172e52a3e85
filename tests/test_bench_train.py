"""``bench train``: its arguments, and the loop's settings on a local Ray instance."""

import json

import pytest

from covers_dist.cli import main


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--settings", "covers_2w,nope"], "unknown setting(s) ['nope']"),
        (["--iterations", "0"], "--iterations must be >= 1"),
    ],
)
def test_bench_train_rejects_bad_arguments(argv, message):
    with pytest.raises(SystemExit) as err:
        main(["bench", "train", "--config", "configs/smoke.yaml", *argv])
    assert message in str(err.value)


@pytest.mark.bench
def test_bench_train_counts_the_policies_each_cnn_setting_starts(capsys):
    # a new (task, copy) every iteration: COVERS-CNN may create policies inside the window, the
    # single-policy CNN loop never does
    argv = ["bench", "train", "--config", "configs/smoke.yaml", "--settings", "covers_cnn_2w,covers_cnn_2w_shared,cnn_2w",
            "--skip-rllib", "--iterations", "2", "--warmup", "1", "--set", "env.max_episode_steps=20", "--set", "clustering.update_every=4",
            "--set", "env.episodes_per_task=4", "--set", "ppo.minibatch_size=40", "--set", "runtime.envs_per_worker=2",
            "--json"]  # fmt: skip
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    single, bank = out["cnn_2w"], out["covers_cnn_2w"]
    assert single["policies"] == 1 and single["policies_created"] == 0 and single["policy_start_s_per_iter"] == 0
    assert bank["policies"] >= 1 + bank["policies_created"]  # policy 0 and the warm-up's, then the window's
    assert (bank["policy_start_s_per_iter"] > 0) == (bank["policies_created"] > 0)
    for r in (single, bank):
        assert r["env_steps"] == 2 * 4 * 20 and r["phase_assign_s"] >= r["policy_start_s_per_iter"]
    # one learner process per policy (and the one started ahead), or one for them all
    shared = out["covers_cnn_2w_shared"]
    assert bank["learner_processes"] == bank["policies"] + 1 and shared["learner_processes"] == 1
    assert single["learner_processes"] == 1
    for r in (single, bank, shared):  # the memory counts every actor: 2 rollout workers, the clustering actor, learners
        assert r["processes"] >= 3 + r["learner_processes"] and 0 < r["learner_peak_rss_gib"] < r["peak_rss_gib"]
    assert out["cnn_shared_learner_memory"] > 0 and out["cnn_shared_learner_speed"] > 0


def test_the_two_thread_setting_gives_its_learner_two_threads_and_the_default_one():
    from covers_dist.bench.train import COVERS_SETTINGS
    from covers_dist.config import load_config
    from covers_dist.runtime.learner import learner_threads

    def threads(name):
        return learner_threads(load_config("configs/stream_cpu.yaml", COVERS_SETTINGS[name][1]))

    assert threads("covers_2w_2threads") == 2 and threads("covers_2w") == 1


def test_the_coarse_stem_setting_changes_only_the_stem():
    import dataclasses

    from covers_dist.bench.train import COVERS_SETTINGS
    from covers_dist.config import load_config

    base = load_config("configs/stream_cpu.yaml", COVERS_SETTINGS["covers_2w"][1])
    coarse = load_config("configs/stream_cpu.yaml", COVERS_SETTINGS["covers_2w_s2d4"][1])
    assert base.network.space_to_depth == 2 and coarse.network.space_to_depth == 4
    assert dataclasses.replace(coarse, network=dataclasses.replace(coarse.network, space_to_depth=2)) == base


@pytest.mark.bench
def test_bench_train_puts_a_two_thread_learner_and_the_coarse_stem_beside_the_default(capsys):
    argv = ["bench", "train", "--config", "configs/smoke.yaml", "--settings", "covers_2w,covers_2w_2threads,covers_2w_s2d4",
            "--skip-rllib", "--iterations", "2", "--warmup", "1", "--set", "env.max_episode_steps=20", "--set", "clustering.update_every=4",
            "--set", "ppo.minibatch_size=40", "--set", "runtime.envs_per_worker=2", "--json"]  # fmt: skip
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    auto, two = out["covers_2w"], out["covers_2w_2threads"]
    assert auto["env_steps"] == two["env_steps"] == 2 * 4 * 20
    assert out["learner_2threads_vs_auto"] == round(two["env_steps_per_s"] / auto["env_steps_per_s"], 3)
    coarse = out["covers_2w_s2d4"]
    assert coarse["env_steps"] == auto["env_steps"] and out["space_to_depth"] == 1  # smoke's own stem
    assert out["s2d4_vs_config"] == round(coarse["env_steps_per_s"] / auto["env_steps_per_s"], 3)
    assert isinstance(out["native_bf16_cpu"], bool)
