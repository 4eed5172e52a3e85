"""Coloured action noise (ppo.noise_beta): every step stays N(0, 1), the spectrum falls as
1/f^beta, the rollout workers use exactly the drawn sequences, and a policy's colour fades to
white as its own training episodes succeed (ppo.noise_fade_success), and only the entries
ppo.noise_entries names get the colour."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from covers_dist.config import ConfigError, NetworkConfig
from covers_dist.envs.toy import ToyTask, toy_layout
from covers_dist.models import build_actor_critic, gaussian_log_prob
from covers_dist.ppo.noise import (
    FADE_WINDOW,
    NoiseSequences,
    coloured_entries,
    coloured_episode,
    coloured_noise,
    faded_beta,
)
from covers_dist.ppo.rollout import run_lockstep
from covers_dist.runtime.driver import Trainer
from covers_dist.runtime.rollout import EpisodeSpec, RolloutWorker
from covers_dist.runtime.tally import EpisodeTally

from test_runtime_serial import tiny_cfg

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _draws(beta: float, n: int = 4000, steps: int = 64, seed: int = 0) -> np.ndarray:
    gen = torch.Generator().manual_seed(seed)
    return torch.stack([coloured_noise(beta, steps, 1, gen)[:, 0] for _ in range(n)]).numpy().astype(np.float64)


@pytest.mark.parametrize("beta", [0.0, 0.5, 1.0, 2.0])
@pytest.mark.parametrize("steps", [64, 75])  # an even length has a Nyquist term, an odd one none
def test_every_step_is_a_standard_normal(beta, steps):
    x = _draws(beta, steps=steps)
    var = x.var(axis=0)  # over 4000 sequences, per step: the standard error of each is ~0.022
    assert np.all(np.abs(x.mean(axis=0)) < 0.1)
    assert 0.9 < var.min() and var.max() < 1.1
    assert abs(np.mean(np.abs(x) < 1.0) - 0.6827) < 0.01  # a normal's mass within one std


def test_white_noise_is_plain_independent_normals():
    a = coloured_noise(0.0, 50, 3, torch.Generator().manual_seed(7))
    b = torch.randn(50, 3, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b)


def test_the_spectrum_falls_as_one_over_f_to_the_beta():
    lag1 = {}
    for beta in (0.0, 1.0, 2.0):
        x = _draws(beta, n=2000, steps=128)
        lag1[beta] = float(np.mean(x[:, 1:] * x[:, :-1]))
        power = (np.abs(np.fft.rfft(x, axis=1)) ** 2).mean(axis=0)[1:]
        freqs = np.fft.rfftfreq(128)[1:]
        slope = np.polyfit(np.log(freqs[:-1]), np.log(power[:-1]), 1)[0]  # Nyquist term excluded: real only
        assert slope == pytest.approx(-beta, abs=0.1)
    assert abs(lag1[0.0]) < 0.05 and 0.5 < lag1[1.0] < 0.9 and lag1[2.0] > 0.95


def test_same_generator_same_noise_and_bad_arguments():
    a = coloured_noise(1.0, 40, 4, torch.Generator().manual_seed(3))
    b = coloured_noise(1.0, 40, 4, torch.Generator().manual_seed(3))
    assert a.shape == (40, 4) and a.dtype == torch.float32 and torch.equal(a, b)
    with pytest.raises(ValueError, match="beta must be >= 0"):
        coloured_noise(-1.0, 10, 2)
    with pytest.raises(ValueError, match="beta must be >= 0"):
        coloured_noise(float("nan"), 10, 2)
    with pytest.raises(ValueError, match="steps >= 1"):
        coloured_noise(1.0, 0, 2)


def test_sequences_run_on_past_their_length():
    seqs = NoiseSequences(1.0, 8, 2, envs=3, generator=torch.Generator().manual_seed(0))
    late = seqs.take(1, 20)  # a third block of env 1
    assert late.shape == (2,) and len(seqs._seqs[1]) == 24 and len(seqs._seqs[0]) == 8
    again = NoiseSequences(1.0, 8, 2, envs=3, generator=torch.Generator().manual_seed(0))
    assert torch.equal(again.take(1, 20), late) and torch.equal(again.take(2, 3), seqs.take(2, 3))


def _model_and_envs(n: int = 3, steps: int = 12):
    model = build_actor_critic(NetworkConfig(channels=[2, 2, 2, 2], hidden=4), toy_layout(16), seed=1)
    model.eval()
    envs = [ToyTask("reach", "e", image_size=16, max_episode_steps=steps) for _ in range(n)]
    return model, envs


@pytest.mark.parametrize("betas", [1.0, [1.0, 0.0, 2.0]])  # one colour, or one per env (ppo.noise_fraction)
def test_lockstep_actions_are_the_mean_plus_std_times_the_drawn_sequences(betas):
    model, envs = _model_and_envs()
    seeds = [10, 11, 12]
    eps = run_lockstep(model, envs, seeds, torch.Generator().manual_seed(5), noise_beta=betas, noise_steps=12)
    expected = NoiseSequences(betas, 12, envs[0].action_space.shape[0], 3, torch.Generator().manual_seed(5))
    std = model.log_std().exp().detach()
    for i, ep in enumerate(eps):
        obs = {"image": ep["image"][:-1], "proprio": ep["proprio"][:-1]}
        means = torch.from_numpy(model.act(obs, deterministic=True)[0])
        noise = torch.stack([expected.take(i, t) for t in range(len(ep["action"]))])
        torch.testing.assert_close(torch.from_numpy(ep["action"]), means + noise * std, rtol=1e-5, atol=1e-5)
        # the log-probabilities are the Gaussian's of the actions taken, as with white noise
        logp = gaussian_log_prob(torch.from_numpy(ep["action"]), means, model.log_std().detach().expand_as(means))
        torch.testing.assert_close(torch.from_numpy(ep["logprob"]), logp, rtol=1e-4, atol=1e-4)
    again = run_lockstep(model, envs, seeds, torch.Generator().manual_seed(5), noise_beta=betas, noise_steps=12)
    white = run_lockstep(model, envs, seeds, torch.Generator().manual_seed(5))
    for a, b, w in zip(eps, again, white):
        np.testing.assert_array_equal(a["action"], b["action"])
        assert not np.array_equal(a["action"], w["action"])
    with pytest.raises(ValueError, match="one noise_beta per env"):
        run_lockstep(model, envs, seeds, None, noise_beta=[1.0, 0.0])
    greedy = run_lockstep(model, envs, seeds, None, deterministic=True, noise_beta=1.0, noise_steps=12)
    plain = run_lockstep(model, envs, seeds, None, deterministic=True)
    for g, p in zip(greedy, plain):  # greedy acting ignores the noise
        np.testing.assert_array_equal(g["action"], p["action"])


def test_act_checks_the_noise_shape():
    model, envs = _model_and_envs(n=1)
    obs, _ = envs[0].reset(seed=0)
    batch = {"image": obs["image"][None], "proprio": obs["proprio"][None]}
    with pytest.raises(ValueError, match="noise must have shape"):
        model.act(batch, noise=torch.zeros(1, 7))


def test_rollout_workers_sample_with_the_configured_colour(tmp_path):
    specs = [EpisodeSpec(i, "reach", "e", 0) for i in range(4)]
    actions = {}
    for beta in (0.0, 1.0, 1.0):
        cfg = tiny_cfg(tmp_path, f"ppo.noise_beta={beta}")
        worker = RolloutWorker(cfg, 0)
        model = build_actor_critic(cfg.network, worker.layout, seed=0)
        eps = worker.sample(specs, 0, 1, model.get_weights())
        worker.close()
        got = np.concatenate([e["action"] for e in eps])
        if beta in actions:
            np.testing.assert_array_equal(actions[beta], got)  # same seed, same noise
        actions[beta] = got
    assert not np.array_equal(actions[0.0], actions[1.0])
    with pytest.raises(ConfigError, match="ppo.noise_beta"):
        tiny_cfg(tmp_path, "ppo.noise_beta=2.5")


def test_the_colour_fades_linearly_with_the_policy_success(tmp_path):
    assert faded_beta(1.0, None, [1.0] * 10) == 1.0  # no fade configured
    assert faded_beta(1.0, 0.2, []) == 1.0  # a new policy searches with the full colour
    assert faded_beta(0.0, 0.2, [0.0] * 10) == 0.0  # white stays white
    assert faded_beta(1.0, 0.2, [0.0] * 10) == 1.0
    assert faded_beta(1.0, 0.2, [1.0] + [0.0] * 9) == pytest.approx(0.5)  # 10% of the way's 20%
    assert faded_beta(2.0, 0.2, [1.0, 0.0, 0.0, 0.0, 0.0]) == 0.0  # at the rate: white
    assert faded_beta(1.0, 0.2, [1.0] * 10) == 0.0  # past it: still white, never negative
    with pytest.raises(ValueError, match="fade_success"):
        faded_beta(1.0, 0.0, [1.0])
    for bad in ("0", "1.5"):
        with pytest.raises(ConfigError, match="ppo.noise_fade_success"):
            tiny_cfg(tmp_path, f"ppo.noise_fade_success={bad}")


def test_the_tally_keeps_each_acting_policy_s_last_successes():
    tally = EpisodeTally(["reach"])
    rows = [{"task": "reach", "episode_index": i, "length": 10, "return": 0.0, "success": float(i % 4 == 0),
             "policy_id": 1 if i < 70 else 2} for i in range(80)]  # fmt: skip
    tally.record(rows, assigned=1)
    assert len(tally.policy_success[1]) == FADE_WINDOW  # the last 64 of its 70
    assert tally.policy_success[1] == [float(i % 4 == 0) for i in range(70 - FADE_WINDOW, 70)]
    assert tally.policy_success[2] == [float(i % 4 == 0) for i in range(70, 80)]  # by the policy that acted


def _noise_column(run_dir):
    return [json.loads(line).get("noise_beta") for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


FADE = ["env.tasks=[reach]", "ppo.noise_beta=1.0", "ppo.noise_fade_success=0.25"]


@pytest.fixture(scope="module")
def faded_run(tmp_path_factory):
    """One serial run of the toy reach group with a fading colour (2400 env steps): its directory."""
    clean = tmp_path_factory.mktemp("faded")
    trainer = Trainer(tiny_cfg(clean, "runtime.total_env_steps=2400", *FADE), log=lambda *_: None)
    trainer.run()
    trainer.close()
    return clean


def test_the_loop_samples_each_batch_with_its_policy_s_faded_colour(faded_run, tmp_path):
    fade, clean = FADE, faded_run
    rows = [json.loads(line) for line in (clean / "metrics.jsonl").read_text().splitlines()]
    episodes = [json.loads(line) for line in (clean / "episodes.jsonl").read_text().splitlines()]
    for row in rows:  # the colour from the episodes the acting policy ran before this batch
        before = [e["success"] for e in episodes if e["iteration"] < row["iteration"]
                  and e["policy_id"] == row["policy_id"]][-FADE_WINDOW:]  # fmt: skip
        expected = 1.0 if not before else max(0.0, 1.0 - (sum(s > 0 for s in before) / len(before)) / 0.25)
        assert row["noise_beta"] == pytest.approx(expected)
    betas = _noise_column(clean)
    assert betas[0] == 1.0 and min(betas) < 1.0  # the toy reach succeeds from the first batches on
    # killed and resumed from its checkpoints, the run samples with the same colours
    resumed = tmp_path / "resumed"
    first = Trainer(tiny_cfg(resumed, "runtime.total_env_steps=1200", "runtime.checkpoint_every=1", *fade),
                    log=lambda *_: None)  # fmt: skip
    first.run()
    first.close()
    second = Trainer(tiny_cfg(resumed, "runtime.total_env_steps=2400", *fade), resume=True, log=lambda *_: None)
    second.run()
    second.close()
    assert _noise_column(resumed) == betas
    assert (resumed / "episodes.jsonl").read_text() == (clean / "episodes.jsonl").read_text()


@pytest.mark.slow
def test_ray_workers_sample_with_the_faded_colour_as_the_serial_loop(ray_local, faded_run, tmp_path):
    """Slow tier (half a minute beside the other pytest worker): the default suite checks the
    colour the driver computes (the serial loop, above) and that a rollout worker samples with the
    colour it is given (below); the chaos test holds a Ray run of two workers to its serial run."""
    trainer = Trainer(tiny_cfg(tmp_path, "runtime.total_env_steps=2400", "runtime.serial=false", *FADE),
                      log=lambda *_: None)  # fmt: skip
    trainer.run()
    trainer.close()
    assert _noise_column(tmp_path) == _noise_column(faded_run)
    assert (tmp_path / "episodes.jsonl").read_text() == (faded_run / "episodes.jsonl").read_text()


def test_a_worker_samples_with_the_colour_it_is_given(tmp_path):
    specs = [EpisodeSpec(i, "reach", "e", 0) for i in range(4)]
    got = {}
    for name, setting, given in (("pink", 1.0, None), ("given", 0.0, 1.0), ("white", 1.0, 0.0)):
        worker = RolloutWorker(tiny_cfg(tmp_path, f"ppo.noise_beta={setting}"), 0)
        model = build_actor_critic(worker.cfg.network, worker.layout, seed=0)
        got[name] = np.concatenate([e["action"] for e in worker.sample(specs, 0, 1, model.get_weights(), noise_beta=given)])
        with pytest.raises(ValueError, match="noise_beta must be in"):
            worker.sample(specs, 0, 1, model.get_weights(), noise_beta=2.5)
        worker.close()
    np.testing.assert_array_equal(got["pink"], got["given"])  # the given colour, not the config's
    assert not np.array_equal(got["pink"], got["white"])


def test_a_fraction_of_the_episodes_gets_the_colour(tmp_path):
    assert [coloured_episode(i, 0.5) for i in range(6)] == [False, True, False, True, False, True]
    assert sum(coloured_episode(i, 0.25) for i in range(100)) == 25
    assert all(coloured_episode(i, 1.0) for i in range(10)) and not any(coloured_episode(i, 0.0) for i in range(10))
    with pytest.raises(ValueError, match="fraction"):
        coloured_episode(0, 1.5)
    specs = [EpisodeSpec(i, "reach", "e", 0) for i in range(4)]
    got = {}
    for name, sets in (("white", ["ppo.noise_beta=0.0"]), ("none", ["ppo.noise_beta=1.0", "ppo.noise_fraction=0.0"]),
                       ("pink", ["ppo.noise_beta=1.0"]), ("all", ["ppo.noise_beta=1.0", "ppo.noise_fraction=1.0"]),
                       ("half", ["ppo.noise_beta=1.0", "ppo.noise_fraction=0.5"])):  # fmt: skip
        worker = RolloutWorker(tiny_cfg(tmp_path, *sets), 0)
        model = build_actor_critic(worker.cfg.network, worker.layout, seed=0)
        got[name] = [e["action"] for e in worker.sample(specs, 0, 1, model.get_weights())]
        worker.close()
    for a, b in ((got["white"], got["none"]), (got["pink"], got["all"])):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    assert not any(np.array_equal(x, y) for x, y in zip(got["half"], got["pink"]))
    with pytest.raises(ConfigError, match="ppo.noise_fraction"):
        tiny_cfg(tmp_path, "ppo.noise_fraction=1.5")


def test_bench_explore_runs_white_first_and_coloured_noise_lifts_the_hand(capsys):
    from covers_dist.cli import main

    argv = ["bench", "explore", "--task", "button-press-topdown-v3", "--betas", "2", "--stds", "1.0", "--episodes", "8",
            "--steps", "150", "--json"]  # fmt: skip
    assert main(argv) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [r["beta"] for r in rows] == [0.0, 2.0]  # white added as the baseline
    for r in rows:
        assert r["episodes"] == 8 and r["success_rate"] == pytest.approx(r["successes"] / 8, abs=1e-4)
        assert r["ci95"][0] <= r["success_rate"] <= r["ci95"][1]
    # white noise averages out along the episode; red noise moves the hand up and down for whole stretches
    assert rows[1]["hand_rise_m_median"] > 2 * rows[0]["hand_rise_m_median"]
    assert all(r["entries"] == "all" for r in rows)
    # red noise on the plane only (ppo.noise_entries=planar): the height stays white, the hand stays low
    assert main([*argv, "--entries", "planar"]) == 0
    planar = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [r["entries"] for r in planar] == ["planar", "planar"]
    assert planar[0] == {**rows[0], "entries": "planar"}  # white noise is white whatever the entries
    assert planar[1]["hand_rise_m_median"] < 0.5 * rows[1]["hand_rise_m_median"]
    for bad, words in (
        (["--task", "button-press-v9"], "unknown Meta-World task"),
        (["--betas", "3"], "--betas values must lie in"),
        (["--stds", "x"], "--stds needs numbers"),
        (["--episodes", "0"], "--episodes and --steps must be >= 1"),
    ):
        with pytest.raises(SystemExit, match=words):
            main(["bench", "explore", *bad])
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:  # argparse's choices: a usage error naming the option
        main(["bench", "explore", "--entries", "z"])
    assert exc.value.code == 2 and "--entries: invalid choice: 'z'" in capsys.readouterr().err


def test_coloured_entries_choose_per_kind_of_entry():
    from typing import get_args, get_type_hints

    from covers_dist.config import PPOConfig
    from covers_dist.ppo.noise import NOISE_ENTRIES

    assert get_args(get_type_hints(PPOConfig)["noise_entries"]) == NOISE_ENTRIES  # the config's choices
    assert coloured_entries("all", 4, 1) is None
    assert coloured_entries("planar", 4, 1) == [True, True, False, False]  # x, y: the group moves them
    assert coloured_entries("scalar", 4, 1) == [False, False, True, True]  # height, gripper
    assert coloured_entries("scalar", 2, 1) == [False, False]  # a layout with no scalar entries: all white
    with pytest.raises(ValueError, match="must be one of all, planar, scalar"):
        coloured_entries("z", 4, 1)
    with pytest.raises(ValueError, match="action_pairs"):
        coloured_entries("planar", 2, 2)


def test_only_the_flagged_entries_are_coloured():
    flags = [False, False, True, True]
    gen = torch.Generator().manual_seed(4)
    x = torch.stack([coloured_noise(1.0, 64, 4, gen, flags) for _ in range(2000)]).numpy().astype(np.float64)
    lag1 = np.mean(x[:, 1:] * x[:, :-1], axis=(0, 1))  # per entry
    assert np.all(np.abs(lag1[:2]) < 0.05) and np.all((lag1[2:] > 0.5) & (lag1[2:] < 0.9))
    var = x.var(axis=0)  # every step of every entry still N(0, 1)
    assert 0.88 < var.min() and var.max() < 1.12
    # the flagged entries are the draws of an all-coloured sequence; all flags set changes nothing
    a = coloured_noise(1.0, 30, 4, torch.Generator().manual_seed(9), flags)
    b = coloured_noise(1.0, 30, 4, torch.Generator().manual_seed(9))
    assert torch.equal(a[:, 2:], b[:, 2:]) and not torch.equal(a[:, :2], b[:, :2])
    assert torch.equal(coloured_noise(1.0, 30, 4, torch.Generator().manual_seed(9), [True] * 4), b)
    with pytest.raises(ValueError, match="one coloured flag per dim"):
        coloured_noise(1.0, 30, 4, None, [True, False])
    seqs = NoiseSequences(1.0, 8, 4, envs=2, generator=torch.Generator().manual_seed(2), coloured=flags)
    late = seqs.take(0, 11)  # a second block keeps the flags
    assert late.shape == (4,) and len(seqs._seqs[0]) == 16


def test_rollout_workers_colour_the_configured_entries(tmp_path):
    specs = [EpisodeSpec(i, "reach", "e", 0) for i in range(4)]
    got = {}
    for entries in ("all", "planar", "scalar"):
        worker = RolloutWorker(tiny_cfg(tmp_path, "ppo.noise_beta=1.0", f"ppo.noise_entries={entries}"), 0)
        model = build_actor_critic(worker.cfg.network, worker.layout, seed=0)
        got[entries] = np.concatenate([e["action"] for e in worker.sample(specs, 0, 1, model.get_weights())])
        worker.close()
    # the toy's two action entries are one table-plane pair: planar colours both, as all does
    np.testing.assert_array_equal(got["planar"], got["all"])
    assert not np.array_equal(got["scalar"], got["all"])
    with pytest.raises(ConfigError, match="ppo.noise_entries"):
        tiny_cfg(tmp_path, "ppo.noise_entries=z")
