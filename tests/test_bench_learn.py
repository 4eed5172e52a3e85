"""`covers-dist bench learn`: argument errors, a short real run on the toy suite, the evaluation
protocol, the race's stopping rules and RLlib's env on the group's transforms."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from covers_dist.bench.learn import AVERAGED_VERSION, GroupEvaluation, peer_budget, race, ratios
from covers_dist.config import config_to_dict, load_config
from covers_dist.symmetry import get_group

ROOT = Path(__file__).resolve().parents[1]
EXE = str(Path(sys.executable).parent / "covers-dist")
D4 = [g.name for g in get_group("D4")]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    env.pop("RAY_ADDRESS", None)
    env["PATH"] = f"{Path(sys.executable).parent}:{env.get('PATH', '')}"
    return env


def _learn_process(*argv: str, timeout: float = 240, tmpdir: str | None = None) -> subprocess.CompletedProcess:
    """`covers-dist bench learn` in its own process (the peers start and stop Ray themselves)."""
    cmd = [EXE, "bench", "learn", "--config", "configs/smoke.yaml", *argv]
    env = _env() if tmpdir is None else {**_env(), "TMPDIR": tmpdir}
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def learn(capsys, monkeypatch):
    """``learn(*ARGV)``: `covers-dist bench learn --config configs/smoke.yaml ARGV` in this process
    (the CLI's main, as the console script calls it); its exit status, stdout and stderr."""
    from covers_dist.cli import main

    monkeypatch.chdir(ROOT)

    def run(*argv: str) -> SimpleNamespace:
        capsys.readouterr()
        try:
            code = main(["bench", "learn", "--config", "configs/smoke.yaml", *argv])
        except SystemExit as e:  # usage errors: exit status 2
            code = e.code
        out = capsys.readouterr()
        return SimpleNamespace(returncode=code, stdout=out.out, stderr=out.err)

    return run


# ---- argument errors -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--task", "no-such-task"], ["unknown", "no-such-task", "reach", "push", "avoid"]),
        (["--threshold", "1.5"], ["--threshold", "(0, 1]"]),
        (["--threshold", "0"], ["--threshold"]),
        (["--contenders", "covers,tf-agents"], ["unknown contender", "tf-agents", "rllib-equi", "sb3"]),
        (["--peer-budget-factor", "0.5"], ["--peer-budget-factor", ">= 1"]),
        (["--eval-every", "0"], ["--eval-every", ">= 1"]),
        (["--keep-runs"], ["--keep-runs", "--out"]),
        (["--contenders", "covers,sb3", "--set", "ppo.log_std_cap=-1.0"], ["ppo.log_std_cap", "sb3"]),
        (["--contenders", "covers,rllib-cnn", "--set", "ppo.ent_schedule=linear"], ["ppo.ent_schedule=linear", "rllib-cnn"]),
        (["--contenders", "covers,rllib-equi", "--set", "network.critic=separate"], ["network.critic", "rllib-equi"]),
        (["--contenders", "covers,sb3", "--set", "ppo.noise_beta=1"], ["ppo.noise_beta=1.0", "sb3"]),
    ],
)
def test_bad_arguments_are_one_line_errors(learn, argv, words):
    res = learn(*argv)
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip()
    assert len(err.splitlines()) == 1, err
    for word in words:
        assert word in err, err
    assert res.stdout == ""


# ---- a short real run ------------------------------------------------------------------------------
def test_short_serial_covers_run_writes_curves(tmp_path, learn):
    out = tmp_path / "out"
    res = learn("--task", "reach", "--contenders", "covers", "--serial", "--budget-steps", "2000",
                "--eval-every", "1000", "--eval-episodes", "2", "--set", "ppo.epochs=1", "--set", "network.channels=[2,4]",
                "--set", "network.hidden=8", "--json", "--out", str(out), "--keep-runs")  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    result = json.loads(res.stdout.strip().splitlines()[-1])
    assert result["task"] == "reach" and result["group"] == "D4" and result["transforms"] == D4
    assert result["threshold"] == 0.9 and result["budget"]["env_steps"] == 2000
    assert set(result["contenders"]) == {"covers"}
    assert result["ratios"] == {}  # nothing to compare with
    assert result["eval"]["episodes_per_transform"] == 2
    covers = result["contenders"]["covers"]
    for key in ("reached", "env_steps_to_threshold", "wall_s_to_threshold", "best_min_success", "curve"):
        assert key in covers
    hp = covers["hyperparameters"]
    assert hp["framework"] == "covers-dist" and hp["epochs"] == 1 and hp["value_clip"] is None
    assert hp["train_batch_env_steps"] == 16 * 25 and hp["reward"]["normalize_return"] is True
    curve = covers["curve"]
    assert len(curve) >= 2
    steps = [p["env_steps"] for p in curve]
    assert steps == sorted(set(steps)) and steps[0] == 0
    walls = [p["train_wall_s"] for p in curve]
    assert walls == sorted(walls)
    for p in curve:
        assert sorted(p["success"]) == sorted(D4)
        assert all(0.0 <= v <= 1.0 for v in p["success"].values())
        assert p["distinct_initial_states"] == 8 * 2 and p["episodes_per_transform"] == 2
        assert p["pooled"]["n"] == 16 and p["pooled"]["successes"] == round(p["mean_success"] * 16)
        assert all(lo <= p["success"][g] <= hi for g, (lo, hi) in p["ci95"].items())
        assert p["min_success"] == min(p["success"].values())
        assert p["mean_success"] == pytest.approx(np.mean(list(p["success"].values())))
    if covers["reached"]:
        assert covers["env_steps_to_threshold"] in steps
    else:
        assert steps[-1] >= 2000 and covers["stopped"] in ("steps", "minutes")
    assert covers["best_min_success"] == max(p["min_success"] for p in curve)
    assert "env steps" in res.stderr and "steps/s" in res.stderr  # progress lines
    assert json.loads((out / "result.json").read_text())["contenders"]["covers"]["curve"] == curve
    assert (out / "curves.png").stat().st_size > 1000
    # --keep-runs: the contender's run directory stays, with its config, logs and a final checkpoint
    kept = out / "runs" / "covers"
    assert (kept / "config.yaml").is_file() and (kept / "episodes.jsonl").is_file()
    assert any((kept / "checkpoints").iterdir())
    assert [m["env_steps"] for m in map(json.loads, (kept / "metrics.jsonl").read_text().splitlines())][-1] >= 2000
    again = learn("--task", "reach", "--contenders", "covers", "--serial", "--budget-steps", "2000",
                  "--out", str(out), "--keep-runs")  # fmt: skip
    assert again.returncode == 2 and "already holds a run" in again.stderr, again.stderr


# ---- evaluation, stopping rules, ratios --------------------------------------------------------------
class _ModelContender:
    """A fixed covers-dist network as the only policy."""

    def __init__(self, model) -> None:
        self.model = model
        self.calls: list[int] = []

    def weights_map(self):
        return {0: (0, self.model.get_weights())}

    def choose(self, obs, group_ids):
        self.calls.append(len(obs["image"]))
        return {"policy_id": 0, "decision": "only", "nearest_distance": None}


def test_group_evaluation_is_deterministic_and_uses_distinct_states(one_torch_thread):
    from covers_dist.envs import suite_layout
    from covers_dist.models import build_actor_critic

    cfg = load_config("configs/smoke.yaml", ["env.tasks=[reach]"])
    model = build_actor_critic(cfg.network, suite_layout("toy", cfg.env.image_size), seed=3).eval()
    evaluator = GroupEvaluation(cfg, "reach", D4, episodes=2, seed=cfg.seed)
    contender = _ModelContender(model)
    try:
        first = evaluator.evaluate(contender)
        again = evaluator.evaluate(contender)
    finally:
        evaluator.close()
    assert first == again
    assert sorted(first["success"]) == sorted(D4) and all(0.0 <= v <= 1.0 for v in first["success"].values())
    assert first["policy"] == {g: 0 for g in D4}
    # per transform and pass: the pair-level choice from its 2 first frames, then each episode's own
    assert contender.calls == [2, 1, 1] * 16
    assert first["episode_policies"] == {g: [0, 0] for g in D4}
    assert first["distinct_initial_states"] == 16 and first["episodes_per_transform"] == 2


def _evaluate_standing_still(cfg, task, elements, action_dim):
    """One GroupEvaluation pass (2 episodes per element) of a policy whose actions are all zero."""
    from covers_dist.evaluation.episodes import GreedyPolicy

    class Still:
        choose = staticmethod(lambda obs, gids: {"policy_id": 0, "decision": "only", "nearest_distance": None})

        def weights_map(self):
            return {0: (0, GreedyPolicy(lambda obs: np.zeros((len(obs["image"]), action_dim), np.float32)))}

    evaluator = GroupEvaluation(cfg, task, elements, episodes=2, seed=0)
    try:
        return evaluator.evaluate(Still())
    finally:
        evaluator.close()


def test_group_evaluation_counts_success_ever_reached_and_refuses_sampling_a_greedy_adapter():
    from covers_dist.evaluation.episodes import GreedyPolicy

    still = _evaluate_standing_still(load_config("configs/smoke.yaml", ["env.tasks=[reach]"]), "reach", ["e", "r"], 2)
    assert still["success"] == {"e": 0.0, "r": 0.0}  # standing still never reaches the goal
    assert still["ci95"]["e"][0] == 0.0 and 0.0 < still["ci95"]["e"][1] < 1.0
    assert still["misses"] == {}  # the toy tasks do not say how close an episode came
    with pytest.raises(ValueError, match="greedily only"):
        GreedyPolicy(lambda obs: obs["proprio"]).act({"image": None, "proprio": np.zeros((1, 2))}, deterministic=False)


def test_group_evaluation_on_meta_world_says_how_far_the_failures_stayed():
    from covers_dist.bench.learn import _misses_text

    cfg = load_config("configs/stream_cpu.yaml", ["env.max_episode_steps=30"])
    still = _evaluate_standing_still(cfg, "reach-v3", ["e", "rf"], 4)
    assert still["success"] == {"e": 0.0, "rf": 0.0}
    assert sorted(still["misses"]) == ["e", "rf"]
    for miss in still["misses"].values():  # a still hand starts ~0.2-0.3 m from a goal of radius 0.05
        assert miss["misses"] == 2 and miss["misses_closest_median"] > 2.0 and miss["near_misses"] == 0
    assert _misses_text(still["misses"]) == "failures: 4 (0 within 1.5 success radii); "
    assert _misses_text({}) == ""


def test_covers_evaluates_each_transform_with_the_policy_the_bank_picks(tmp_path, one_torch_thread):
    from covers_dist.bench.learn import _CoversContender
    from covers_dist.evaluation.protocol import pair_seeds

    # a tiny threshold: every iteration creates a policy, so the bank holds several
    cfg = load_config("configs/smoke.yaml", [
        "env.tasks=[reach]", "env.episodes_per_task=1", "runtime.serial=true", "runtime.method=covers-cnn",
        "network.kind=cnn", "clustering.threshold=0.000001", "ppo.epochs=1", f"runtime.run_dir={tmp_path}",
    ])  # fmt: skip
    contender = _CoversContender(cfg)
    evaluator = GroupEvaluation(cfg, "reach", D4, episodes=2, seed=cfg.seed)
    try:
        for _ in range(3):
            contender.train_once()
        contender.before_eval()
        policies = sorted(contender.trainer.weights.versions)
        assert len(policies) > 1 and contender.env_steps == 3 * 16 * 25
        out = evaluator.evaluate(contender)
        chosen = out["policy"]
        assert sorted(out["success"]) == sorted(D4) and set(chosen.values()) <= set(policies)
        worker = evaluator.executors.workers[0]
        for pair in evaluator.pairs:  # each episode: the bank's what-if choice on its own first frame
            first = worker.eval_first_frames([(pair, pair_seeds(cfg.seed, pair, 2))])[0]
            own = [contender.choose({k: v[i : i + 1] for k, v in first.items()}, [0])["policy_id"] for i in range(2)]
            assert out["episode_policies"][pair.g] == own
            assert chosen[pair.g] == max(set(own), key=lambda q: (own.count(q), -q))
        assert evaluator.evaluate(contender) == out
    finally:
        evaluator.close()
        contender.close()


def test_covers_training_does_not_depend_on_when_it_is_evaluated(tmp_path, one_torch_thread):
    """The evaluation acts with the update in flight without publishing it: a run evaluated after
    every iteration trains exactly as one never evaluated (pipelined loop, serial backend)."""
    from covers_dist.bench.learn import _CoversContender

    runs = []
    for name, evaluate, extra in (("plain", False, []), ("evaluated", True, []), ("averaged", True, ["ppo.weight_average=0.9"])):
        cfg = load_config("configs/smoke.yaml", [
            "env.tasks=[reach]", "env.episodes_per_task=1", "runtime.serial=true", "ppo.epochs=1",
            "runtime.pipeline=true", "network.channels=[2,4]", "network.hidden=8", f"runtime.run_dir={tmp_path / name}",
            *extra,
        ])  # fmt: skip
        contender = _CoversContender(cfg)
        evaluator = GroupEvaluation(cfg, "reach", D4[:2], episodes=1, seed=cfg.seed)
        try:
            for _ in range(4):
                contender.train_once()
                if evaluate:
                    contender.before_eval()
                    evaluator.evaluate(contender)
                    for shadow in contender.shadows().values():
                        evaluator.evaluate(SimpleNamespace(choose=contender.choose, weights_map=lambda w=shadow: dict(w)))
            version, weights = contender.trainer.backend.call_learner(0, "weights")
            runs.append((version, contender.trainer.weights.versions[0], weights))
            if extra:  # ppo.weight_average: the evaluation acted with the learner's average, the newest beside it
                (acted_version, acted), = contender.weights_map().values()
                (_, newest), = contender.shadows()["newest"].values()
                assert acted_version < AVERAGED_VERSION
                average = contender.trainer.backend.call_learner(0, "averaged_weights")[1]
                assert all(torch.equal(acted[k], average[k]) for k in acted)
                assert all(torch.equal(newest[k], weights[k]) for k in newest)
                assert not all(torch.equal(acted[k], weights[k]) for k in acted)
            else:
                assert contender.shadows() == {}
        finally:
            evaluator.close()
            contender.close()
    (v1, published1, w1), *others = runs
    for v2, published2, w2 in others:  # evaluating, and evaluating an average too, change nothing in training
        assert (v1, published1) == (v2, published2)
        assert all(torch.equal(w1[k], w2[k]) for k in w1)


class _FakeContender:
    def __init__(self, per_iter: int, success_at: int | None, lucky_at: int | None = None) -> None:
        self.env_steps, self.per_iter, self.success_at, self.lucky_at = 0, per_iter, success_at, lucky_at
        self.drains = 0

    def train_once(self) -> None:
        self.env_steps += self.per_iter

    def before_eval(self) -> None:
        self.drains += 1

    def extra(self):
        return {}


class _FakeEvaluator:
    def evaluate(self, contender):
        steps = contender.env_steps
        hit = (contender.success_at is not None and steps >= contender.success_at) or steps == contender.lucky_at
        success = {g: (1.0 if hit else 0.5 if g == "e" else 0.0) for g in D4}
        return {"success": success, "ci95": {g: [0.0, 1.0] for g in D4}, "policy": {g: 0 for g in D4},
                "pooled": {"successes": 0, "n": 128, "ci95": [0.0, 0.03]},
                "episodes_per_transform": 16, "distinct_initial_states": 128}  # fmt: skip


def test_race_is_solved_at_two_evaluations_in_a_row_or_stops_at_the_budget():
    fast = _FakeContender(per_iter=300, success_at=1500)
    res = race("fake", fast, _FakeEvaluator(), 0.9, 1000, 10_000, 600.0, log=lambda _: None)
    assert res["reached"] and res["stopped"] == "threshold"
    assert [p["env_steps"] for p in res["curve"]] == [0, 1200, 2100, 3000]  # first evaluation past each multiple
    assert [p["held"] for p in res["curve"]] == [0, 0, 1, 2]
    assert res["env_steps_to_threshold"] == 3000 and res["first_met_env_steps"] == 2100
    assert res["first_at_threshold_env_steps"] == 2100
    assert res["best_min_success"] == 1.0
    assert fast.drains == 4 and fast.env_steps == 3000  # stops training at once
    assert all(p["distinct_initial_states"] == 128 for p in res["curve"])

    # one lucky point on the curve does not solve the run
    lucky = _FakeContender(per_iter=300, success_at=None, lucky_at=1200)
    res = race("fake", lucky, _FakeEvaluator(), 0.9, 1000, 3000, 600.0, log=lambda _: None)
    assert not res["reached"] and res["best_min_success"] == 1.0 and res["stopped"] == "steps"
    # met once, never held: the point is reported, the run is not solved
    assert res["first_met_env_steps"] is None and res["first_at_threshold_env_steps"] == 1200

    slow = _FakeContender(per_iter=400, success_at=None)
    res = race("fake", slow, _FakeEvaluator(), 0.9, 1000, 1500, 600.0, log=lambda _: None)
    assert not res["reached"] and res["stopped"] == "steps" and res["env_steps_to_threshold"] is None
    assert res["first_at_threshold_env_steps"] is None
    assert [p["env_steps"] for p in res["curve"]] == [0, 1200, 1600]  # the budget's end is evaluated too
    assert res["best_min_success"] == 0.0 and res["best_mean_success"] == pytest.approx(0.5 / 8)


class _AveragedContender(_FakeContender):
    """Acts with "averaged" weights and has the "newest" evaluated beside them (as ppo.weight_average does)."""

    def weights_map(self):
        return {0: (-1, "averaged")}

    def shadows(self):
        return {"newest": {0: (-2, "newest")}}

    def choose(self, first_frames, group_ids):
        return {"policy_id": 0, "decision": "only", "nearest_distance": None}


class _WeightsEvaluator(_FakeEvaluator):
    """Success 1 on every transform where the weights it is given have succeeded by then."""

    def __init__(self, trained, success_from):
        self.trained, self.success_from = trained, success_from

    def evaluate(self, contender):
        which = contender.weights_map()[0][1]
        hit = self.trained.env_steps >= self.success_from[which] or self.trained.env_steps == 1200 and which == "newest"
        out = _FakeEvaluator.evaluate(self, SimpleNamespace(env_steps=0, success_at=None, lucky_at=None))
        return {**out, "success": {g: (1.0 if hit else 0.0) for g in D4}}


def test_race_evaluates_the_shadow_weights_on_the_same_points_and_stops_on_its_own():
    trained = _AveragedContender(per_iter=300, success_at=None)
    res = race("fake", trained, _WeightsEvaluator(trained, {"averaged": 1500, "newest": 3000}), 0.9, 1000,
               10_000, 600.0, log=lambda _: None)  # fmt: skip
    assert res["reached"] and res["env_steps_to_threshold"] == 3000  # the contender's own weights decide
    newest = [p["shadows"]["newest"] for p in res["curve"]]
    assert [q["min_success"] for q in newest] == [0.0, 1.0, 0.0, 1.0]  # 0, 1200 (lucky), 2100, 3000
    assert [q["held"] for q in newest] == [0, 1, 0, 1]
    assert res["shadows"] == {
        "newest": {"first_at_threshold_env_steps": 1200, "env_steps_to_threshold": None, "best_min_success": 1.0}
    }
    assert res["eval_s"] >= sum(q["eval_s"] for q in newest)
    plain = race("fake", _FakeContender(per_iter=300, success_at=1500), _FakeEvaluator(), 0.9, 1000, 10_000, 600.0,
                 log=lambda _: None)  # fmt: skip
    assert "shadows" not in plain and all("shadows" not in p for p in plain["curve"])


def test_ratios_need_both_contenders_to_reach():
    done = {"reached": True, "wall_s_to_threshold": 10.0, "env_steps_to_threshold": 4000}
    other = {"reached": True, "wall_s_to_threshold": 40.0, "env_steps_to_threshold": 8000}
    r = ratios({"covers": done, "rllib-equi": other, "cnn": {"reached": False}})
    assert r["covers_wall_vs_rllib_equi"] == 0.25 and r["covers_steps_vs_rllib_equi"] == 0.5
    assert r["covers_wall_vs_cnn"] is None and r["covers_steps_vs_cnn"] is None
    assert ratios({"covers": done}) == {}


def test_peers_get_a_multiple_of_what_covers_needed():
    import argparse

    args = argparse.Namespace(budget_steps=200_000, budget_minutes=10.0, peer_budget_factor=4.0)
    assert peer_budget(args, None) == (200_000, 10.0)
    assert peer_budget(args, {"reached": False}) == (200_000, 10.0)
    solved = {"reached": True, "env_steps_to_threshold": 120_000, "wall_s_to_threshold": 600.0}
    assert peer_budget(args, solved) == (480_000, 40.0)


# ---- RLlib's env on the group's transforms --------------------------------------------------------------
def test_image_only_task_draws_transforms_from_the_reset_seed():
    from covers_dist.bench.rllib_peer import ImageOnlyTask

    cfg = load_config("configs/smoke.yaml", ["env.tasks=[reach]"])
    env = ImageOnlyTask({"config": config_to_dict(cfg), "task": "reach", "transforms": D4})
    drawn = []
    for seed in range(12):
        obs, _ = env.reset(seed=seed)
        g = env.g.name
        again, _ = env.reset(seed=seed)
        assert env.g.name == g and np.array_equal(obs, again)  # the same seed: the same g and instance
        assert obs.dtype == np.float32 and obs.shape == (32, 32, 3) and 0.0 <= obs.min() and obs.max() <= 1.0
        drawn.append(g)
    assert len(set(drawn)) >= 4
    # auto-resets (no seed) go on reproducibly from the last seeded reset
    env.reset(seed=5)
    tail = [(env.reset()[0].sum(), env.g.name) for _ in range(6)]
    env.reset(seed=5)
    assert [(env.reset()[0].sum(), env.g.name) for _ in range(6)] == tail
    assert len({g for _, g in tail}) > 1
    env.close()
    plain = ImageOnlyTask({"config": config_to_dict(cfg), "task": "reach"})
    for seed in range(4):
        plain.reset(seed=seed)
        assert plain.g.name == "e"  # bench train's behaviour: the identity only
    plain.close()
    with pytest.raises(ValueError, match="transforms"):
        ImageOnlyTask({"config": config_to_dict(cfg), "task": "reach", "transforms": []})


def assert_equal_terms(hp: dict, cfg) -> None:
    """A peer's hyperparameters, read back from the built algorithm, are covers-dist's for ``cfg``."""
    from covers_dist.bench.rllib_peer import ppo_settings

    want = ppo_settings(cfg)
    for key in ("train_batch_env_steps", "minibatch_size", "epochs", "lr_schedule", "lr_horizon_updates", "value_clip"):
        assert hp[key] == want[key], (key, hp[key], want[key])
    for key in ("lr", "gamma", "gae_lambda", "clip", "max_grad_norm", "ent_coef", "vf_coef"):
        assert hp[key] == pytest.approx(want[key]), (key, hp[key], want[key])
    for key in ("scale", "normalize_return"):
        assert hp["reward"][key] == want["reward"][key], (key, hp["reward"], want["reward"])
    if hp["framework"] == "stable-baselines3":  # SB3's own early stop at the same approximate KL
        assert hp["target_kl"] == pytest.approx(want["target_kl"]) and hp["kl_loss"] is False
    else:  # RLlib has no KL stop: its KL loss stands in where covers-dist stops
        assert hp["kl_loss"] is (want["target_kl"] is not None)


@pytest.mark.slow
def test_short_peer_runs_on_equal_terms(short_tmpdir):
    """RLlib on the project's CNN twin and SB3's PPO, one iteration each: the same PPO settings as
    covers-dist, read back from the built algorithms, and the same evaluation. The Ray instance
    the RLlib peer starts leaves no temp dir behind. Slow tier (about a minute on 2 cores, most of
    it starting the peers' processes): the default suite reads the same settings back from each
    peer built in its own process (the SB3 temp-directory test below, tests/test_rllib_module.py)."""
    res = _learn_process("--task", "reach", "--contenders", "rllib-cnn,sb3", "--budget-steps", "400", "--eval-every", "400",
                 "--eval-episodes", "1", "--set", "runtime.num_workers=1", "--set", "env.image_size=48",
                 "--set", "ppo.lr_schedule=linear", "--set", "ppo.target_kl=0.02", "--json", timeout=400,
                 tmpdir=str(short_tmpdir))  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "learn rllib-cnn: ready" in res.stderr and list(short_tmpdir.glob("covers-ray-*")) == []
    result = json.loads(res.stdout.strip().splitlines()[-1])
    for name, framework in (("rllib-cnn", "rllib"), ("sb3", "stable-baselines3")):
        entry = result["contenders"][name]
        assert entry["backend"] in ("rllib", "sb3") and entry["setup_s"] > 0
        assert [p["env_steps"] for p in entry["curve"]] == [0, 400]
        assert all(sorted(p["success"]) == sorted(D4) and p["distinct_initial_states"] == 8 for p in entry["curve"])
        hp = entry["hyperparameters"]
        assert hp["framework"] == framework and hp["observation"] == "image + proprio"
        assert (hp["train_batch_env_steps"], hp["epochs"], hp["minibatch_size"]) == (16 * 25, 4, 200)
        assert (hp["lr"], hp["gamma"], hp["gae_lambda"], hp["clip"]) == (1e-3, 0.99, 0.95, 0.2)
        # the linear schedule ends with the peer's own budget: 400 env steps, one batch
        assert (hp["lr_schedule"], hp["lr_horizon_updates"]) == ("linear", 1)
        assert hp["value_clip"] is None and hp["max_grad_norm"] == 0.5
        # the KL stop: SB3's own early stop at the same approximate KL; RLlib has none, its KL loss stands in
        if name == "sb3":
            assert hp["target_kl"] == pytest.approx(0.02) and hp["kl_loss"] is False
        else:
            assert hp["kl_loss"] is True
        assert hp["reward"]["scale"] == 0.1 and hp["reward"]["normalize_return"] is True


def test_sb3_training_leaves_nothing_in_the_temp_directory(tmp_path, monkeypatch):
    """SB3's default logger makes an empty ``SB3-<time>`` folder in the temp directory at every
    ``learn()`` call (``bench learn`` makes one a batch: hundreds of folders a run); the peer's
    logger writes nothing."""
    import tempfile

    from covers_dist.bench.sb3_peer import build_sb3_ppo, sb3_hyperparameters

    cfg = load_config(str(ROOT / "configs" / "smoke.yaml"),
                      ["env.tasks=[reach]", "env.image_size=48", "runtime.num_workers=1", "runtime.envs_per_worker=1",
                       "ppo.epochs=1", "ppo.lr_schedule=linear", "ppo.target_kl=0.02"])  # fmt: skip
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    model = build_sb3_ppo(cfg, ["e", "r"])
    # on equal terms: covers-dist's PPO settings, read back from the built model
    assert_equal_terms(sb3_hyperparameters(model, cfg), cfg)
    for _ in range(2):
        model.learn(total_timesteps=model.n_steps * model.n_envs, reset_num_timesteps=False)
    assert model.num_timesteps > 0
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("SB3-")] == []


# ---- joining separate invocations --------------------------------------------------------------------
def _result(contenders: dict, **top) -> dict:
    base = {"task": "reach", "group": "D4", "transforms": D4, "threshold": 0.9,
            "eval": {"every_env_steps": 1000, "episodes_per_transform": 2}, "budget": {"env_steps": 2000, "minutes": 1.0},
            "config": "configs/smoke.yaml", "overrides": [], "seed": 0, "contenders": contenders}  # fmt: skip
    base.update(top)
    return base


def _entry(reached: bool, steps: int | None, wall: float | None) -> dict:
    curve = [{"env_steps": 0, "train_wall_s": 0.0, "min_success": 0.0, "mean_success": 0.0}]
    if reached:
        curve.append({"env_steps": steps, "train_wall_s": wall, "min_success": 1.0, "mean_success": 1.0})
    return {"reached": reached, "env_steps_to_threshold": steps, "wall_s_to_threshold": wall, "curve": curve}


def test_merge_joins_separate_invocations_and_recomputes_ratios(tmp_path, learn):
    a = tmp_path / "a.json"
    b = tmp_path / "b.json"
    a.write_text(json.dumps(_result({"covers": _entry(True, 1000, 10.0)}, ratios={})))
    b.write_text(json.dumps(_result({"cnn": _entry(True, 4000, 20.0), "rllib": _entry(True, 2000, 40.0)},
                                    budget={"env_steps": 9000, "minutes": 3.0}, seed=1, ratios={})))  # fmt: skip
    out = tmp_path / "out"
    res = learn("--merge", str(a), str(b), "--json", "--out", str(out))
    assert res.returncode == 0, res.stderr
    merged = json.loads(res.stdout.strip().splitlines()[-1])
    assert list(merged["contenders"]) == ["covers", "cnn", "rllib"]
    assert merged["ratios"] == {"covers_wall_vs_rllib": 0.25, "covers_steps_vs_rllib": 0.5,
                                "covers_wall_vs_cnn": 0.5, "covers_steps_vs_cnn": 0.25}  # fmt: skip
    assert merged["contenders"]["cnn"]["budget"] == {"env_steps": 9000, "minutes": 3.0}
    assert merged["contenders"]["cnn"]["seed"] == 1 and merged["contenders"]["covers"]["seed"] == 0
    assert merged["merged_from"] == [str(a), str(b)]
    assert json.loads((out / "result.json").read_text()) == merged
    assert (out / "curves.png").stat().st_size > 1000


@pytest.mark.parametrize(
    ("second", "words"),
    [
        (_result({"cnn": _entry(False, None, None)}, task="push"), ["task", "'push'", "'reach'"]),
        (_result({"cnn": _entry(False, None, None)}, threshold=0.8), ["threshold", "0.8"]),
        (_result({"covers": _entry(False, None, None)}), ["covers", "more than one"]),
        ({"task": "reach"}, ["not a bench learn result", "contenders"]),
        (_result([1, 2]), ["not a bench learn result", "contenders"]),
        (_result({"cnn": 3}), ["not a bench learn result", "contenders"]),
        ([1, 2], ["not a bench learn result"]),
        (_result({"cnn": {"reached": False}}), ["'cnn'", "no curve"]),
        (_result({"cnn": {**_entry(False, None, None), "curve": [{"env_steps": 0, "min_success": 0.0}]}}),
         ["'cnn'", "curve point 0", "train_wall_s", "mean_success"]),
        (_result({"cnn": {**_entry(False, None, None), "curve": [None]}}), ["curve point 0", "env_steps"]),
    ],
)
def test_merge_refuses_results_that_do_not_compare(tmp_path, learn, second, words):
    a = tmp_path / "a.json"
    b = tmp_path / "b.json"
    a.write_text(json.dumps(_result({"covers": _entry(True, 1000, 10.0)})))
    b.write_text(json.dumps(second))
    res = learn("--merge", str(a), str(b))
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip()
    assert len(err.splitlines()) == 1 and err.startswith("covers-dist bench learn: --merge:"), err
    for word in words:
        assert word in err, err
    assert res.stdout == ""


def test_merge_checks_the_first_result_too(tmp_path, learn):
    a = tmp_path / "a.json"
    b = tmp_path / "b.json"
    a.write_text(json.dumps({"contenders": {}}))
    b.write_text(json.dumps(_result({"covers": _entry(True, 1000, 10.0)})))
    res = learn("--merge", str(a), str(b))
    assert res.returncode == 2 and "not a bench learn result" in res.stderr and "a.json" in res.stderr, res.stderr


def test_merge_names_a_missing_or_corrupt_file(tmp_path, learn):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    for path, words in ((tmp_path / "missing.json", ["no such file", "missing.json"]), (bad, ["cannot read", "bad.json"])):
        res = learn("--merge", str(path))
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
        assert all(w in res.stderr for w in words), res.stderr


# ---- several results in one figure --------------------------------------------------------------------
def test_figure_draws_results_of_several_task_groups_in_one_png(tmp_path, learn):
    paths = []
    for i, (task, entry) in enumerate((("reach", _entry(True, 1000, 10.0)), ("push", _entry(False, None, None)),
                                       ("reach", _entry(False, None, None)))):  # fmt: skip
        path = tmp_path / f"r{i}.json"
        path.write_text(json.dumps(_result({"covers": entry}, task=task, seed=i, overrides=[f"seed={i}", "a=1"])))
        paths.append(str(path))
    out = tmp_path / "fig" / "groups.png"
    res = learn("--figure", ",".join(paths), "--plot", str(out))
    assert res.returncode == 0, res.stderr
    assert out.stat().st_size > 1000 and "figure written" in res.stderr
    from covers_dist.bench.learn import _default_labels

    # the labels name what differs between the results, not what they share
    assert _default_labels([json.loads(open(p).read()) for p in paths]) == ["seed 0 seed=0", "seed 1 seed=1",
                                                                            "seed 2 seed=2"]  # fmt: skip


def test_figure_with_many_curves_puts_the_legend_under_the_axes(tmp_path, learn):
    import struct

    from covers_dist.bench.learn import LEGEND_INSIDE

    def height(png):  # the IHDR chunk: width and height, big-endian, after the 16-byte header
        return struct.unpack(">II", png.read_bytes()[16:24])[1]

    heights = []
    for n in (LEGEND_INSIDE, LEGEND_INSIDE + 4):
        paths = []
        for i in range(n):
            path = tmp_path / f"n{n}-r{i}.json"
            path.write_text(json.dumps(_result({"covers": _entry(False, None, None)}, seed=i, overrides=[f"seed={i}"])))
            paths.append(str(path))
        out = tmp_path / f"many{n}.png"
        assert learn("--figure", ",".join(paths), "--plot", str(out)).returncode == 0
        heights.append(height(out))
    assert heights[1] > heights[0] * 1.3  # the labels got their own room instead of covering the curves


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        ([], ["--figure", "--plot"]),
        (["--plot", "x.png", "--labels", "a,b"], ["--labels", "2 labels", "1 result"]),
        (["--plot", "x.png", "--figure", "missing.json"], ["--figure", "no such file", "missing.json"]),
    ],
)
def test_figure_refuses_bad_arguments_with_one_line(tmp_path, learn, argv, words):
    good = tmp_path / "good.json"
    good.write_text(json.dumps(_result({"covers": _entry(True, 1000, 10.0)})))
    res = learn("--figure", str(good), *[str(tmp_path / a) if a.endswith((".png", ".json")) else a for a in argv])
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert all(w in res.stderr for w in words), res.stderr


def test_figure_refuses_a_file_that_is_not_a_result(tmp_path, learn):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"task": "reach", "contenders": {"covers": {"curve": [None]}}, "threshold": 0.9}))
    res = learn("--figure", str(bad), "--plot", str(tmp_path / "x.png"))
    assert res.returncode == 2 and "--figure" in res.stderr and "curve point 0" in res.stderr, res.stderr
    assert not (tmp_path / "x.png").exists()


# ---- seeds summed up ------------------------------------------------------------------------------------
def _seed_results(tmp_path, runs, **top) -> list[str]:
    """One result file per (task, seed, entry) of ``runs``; their paths."""
    paths = []
    for task, seed, entry in runs:
        path = tmp_path / f"{task}-s{seed}.json"
        path.write_text(json.dumps(_result({"covers": entry}, task=task, seed=seed,
                                           overrides=[f"seed={seed}", "ppo.epochs=4"], **top)))  # fmt: skip
        paths.append(str(path))
    return paths


def test_table_gives_each_group_its_seeds_held_and_censored_median(tmp_path, learn):
    paths = _seed_results(tmp_path, [
        ("reach", 0, _entry(True, 1000, 60.0)), ("reach", 1, _entry(True, 3000, 180.0)),
        ("reach", 2, _entry(False, None, None)), ("push", 0, _entry(True, 2000, 90.0)),
        ("push", 1, _entry(False, None, None)),
    ])  # fmt: skip
    res = learn("--table", ",".join(paths), "--json")
    assert res.returncode == 0, res.stderr
    reach, push = json.loads(res.stdout.strip().splitlines()[-1])
    assert (reach["task"], reach["seeds"], reach["held"], reach["n"]) == ("reach", [0, 1, 2], 2, 3)
    # the run that did not hold counts as later than both that did: the median is the second of three
    assert reach["env_steps_to_held"] == {"median": 3000.0, "min": 1000.0, "max": 3000.0}
    assert reach["minutes_to_held"] == {"median": 3.0, "min": 1.0, "max": 3.0}
    # one of two held: half the seeds are past the budget, so there is no median, only the range
    assert push["env_steps_to_held"] == {"median": None, "min": 2000.0, "max": 2000.0}
    assert push["setting"]["overrides"] == ["ppo.epochs=4"]
    text = learn("--table", ",".join(paths))
    assert text.returncode == 0, text.stderr
    lines = text.stdout.strip().splitlines()
    assert lines[0].startswith("| task group |") and "held within 2k env steps or 1 min" in lines[0]
    assert "| reach | covers | 2 of 3 (seeds 0, 1) | 3k (1k-3k; 1 later than the budget) | 3.0 (1.0-3.0;" in lines[2]
    assert "seed 2: 0.00/0.00 at 0" in lines[2]
    assert "| push | covers | 1 of 2 (seeds 0) | not held (2k; 1 later than the budget) |" in lines[3]


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"overrides": ["ppo.epochs=2"]}, ["overrides", "ppo.epochs=2", "one setting"]),
        ({"threshold": 0.8}, ["threshold", "0.8"]),
        ({"budget": {"env_steps": 9000, "minutes": 1.0}}, ["budget", "9000"]),
        ({"seed": 0}, ["seed 0", "more than one result"]),
        ({"contenders": {"covers": {"reached": True, "curve": []}}}, ["held but has no env steps"]),
        ({"contenders": {"covers": 3}}, ["not a bench learn result"]),
        ({"task": None, "contenders": None}, ["not a bench learn result"]),
    ],
)
def test_table_refuses_runs_of_other_settings_or_a_repeated_seed(tmp_path, learn, change, words):
    good = _seed_results(tmp_path, [("reach", 0, _entry(True, 1000, 60.0))])[0]
    second = _result({"covers": _entry(False, None, None)}, seed=1, overrides=["seed=1", "ppo.epochs=4"])
    second.update(change)
    bad = tmp_path / "second.json"
    bad.write_text(json.dumps({k: v for k, v in second.items() if v is not None}))
    res = learn("--table", good, str(bad))
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip()
    assert len(err.splitlines()) == 1 and err.startswith("covers-dist bench learn: --table:"), err
    assert all(w in err for w in words), err
    assert res.stdout == ""


def test_table_names_a_missing_file(tmp_path, learn):
    res = learn("--table", str(tmp_path / "missing.json"))
    assert res.returncode == 2 and "--table" in res.stderr and "no such file" in res.stderr, res.stderr
