"""Evaluation of every (task, g): the protocol, the continual-learning metrics (against hand-computed
answers), passes during a serial training run, `covers-dist eval` / `report` on a saved run (read-only,
deterministic, clear errors), and evaluation executors on Ray giving the same pass as local ones."""

import hashlib
import json
import shutil

import numpy as np
import pytest
import torch

from covers_dist.cli import main
from covers_dist.config import load_config
from covers_dist.envs.stream import TaskStream
from covers_dist.evaluation import (
    LocalExecutors,
    continual_metrics,
    eval_pairs,
    eval_seed,
    forgetting,
    forward_transfer,
    metric_row,
    oracle_policies,
    pass_summary,
    read_passes,
    run_evaluation,
)
from covers_dist.evaluation.metrics import group_success, group_worst, held_groups
from covers_dist.evaluation.protocol import EvalPair, pair_rows, pair_seeds, plan_jobs
from covers_dist.runtime import evaluation as runtime_evaluation
from covers_dist.runtime.driver import Trainer
from covers_dist.runtime.rollout import episode_seed
from covers_dist.symmetry import get_group

TASKS = ["reach", "push", "avoid"]
# 3 iterations of 8 episodes x 25 steps; 24 (task, g) pairs, 2 of them held out
TINY = [
    "runtime.serial=true",
    "runtime.num_workers=1",
    "runtime.envs_per_worker=4",
    "env.episodes_per_task=8",
    "env.max_episode_steps=25",
    "env.held_out=2",
    "clustering.update_every=8",
    "ppo.epochs=1",
    "ppo.minibatch_size=200",
    "network.channels=[2,4]",
    "network.hidden=8",
    "runtime.log_every_s=1000",
    "runtime.total_env_steps=600",
    "runtime.checkpoint_every=100",
    "eval.episodes=2",
    # sequential: no update in flight at the end, so the final pass's bank (its published encoders)
    # is the checkpoint's; a pipelined run's checkpoint holds the in-flight update's newest weights,
    # and `covers-dist eval` may then choose another policy than the final pass did
    "runtime.pipeline=false",
    # each policy's own encoder: at this width the joint features keep the toy groups on one policy,
    # and these tests need two
    "clustering.feature_source=own",
]
KEYS = {f"{m}/{s}" for m in ("greedy", "stochastic") for s in ("agnostic", "oracle")}


def tiny_cfg(run_dir, *extra):
    return load_config("configs/smoke.yaml", [*TINY, f"runtime.run_dir={run_dir}", *extra])


def train(run_dir, *extra):
    trainer = Trainer(tiny_cfg(run_dir, *extra), log=lambda *_: None)
    result = trainer.run()
    trainer.close()
    assert result["status"] == "finished"
    return result


def lines(path):
    return [json.loads(x) for x in path.read_text().splitlines()]


def snapshot(root):
    """{relative path: sha256} of every file under ``root``."""
    files = sorted(p for p in root.rglob("*") if p.is_file())
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


@pytest.fixture(scope="module")
def runs(tmp_path_factory, one_torch_thread):
    """The same tiny serial run with evaluation of 2 of its 3 tasks every 2 iterations (+ the final
    pass) and without evaluation."""
    root = tmp_path_factory.mktemp("eval-runs")
    train(root / "on", "eval.every_iterations=2", "eval.tasks=[reach,push]")
    train(root / "off", "eval.every_iterations=0")
    return root / "on", root / "off"


@pytest.fixture(scope="module")
def equi_run(tmp_path_factory, one_torch_thread):
    """The "on" run's config with one shared equivariant policy (runtime.method=equi): the other
    method of the comparisons (read-only there)."""
    equi = tmp_path_factory.mktemp("eval-equi") / "equi"
    train(equi, "runtime.method=equi", "eval.every_iterations=2", "eval.tasks=[reach,push]")
    return equi


# ---- metrics against hand-computed answers -------------------------------------------------------
def row(task, g, status, success, ret=0.0, oracle=None, stochastic=None):
    results = {"greedy/agnostic": {"success": success, "return": ret}}
    if oracle is not None:
        results["greedy/oracle"] = {"success": oracle, "return": ret}
    if stochastic is not None:
        results["stochastic/agnostic"] = {"success": stochastic, "return": ret}
    return {"task": task, "g": g, "status": status, "results": results}


def fake_pass(iteration, rows, groups):
    return {"iteration": iteration, "pairs": rows, "groups": groups}


def seen(*tasks, steps=None):
    steps = steps or {}
    return {t: {"first_episode": 0 if t in tasks else None, "env_steps": steps.get(t, 0)} for t in ("A", "B", "C")}


def test_pass_summary_separates_seen_held_out_and_trainable_and_averages_seen_groups():
    ev = fake_pass(
        5,
        [
            row("A", "e", "seen", 1.0, ret=2.0, oracle=1.0, stochastic=0.0),
            row("A", "r", "seen", 0.5, ret=4.0, oracle=0.0),
            row("A", "f", "unseen", 0.0, ret=6.0),
            row("A", "h", "held_out", 1.0, ret=100.0),
            row("B", "e", "seen", 0.0),
            row("B", "h", "held_out", 0.0),
            {"task": "B", "g": "r", "status": "seen", "results": {}},  # no policy ran: left out, not a zero
            row("C", "e", "unseen", 1.0),  # C not shown yet: not in the average
        ],
        seen("A", "B"),
    )
    s = pass_summary(ev)
    a, b, c = s["groups"]["A"], s["groups"]["B"], s["groups"]["C"]
    assert a["success"] == pytest.approx(0.5)  # trainable pairs (seen + unseen): (1 + 0.5 + 0) / 3
    assert a["success_seen"] == pytest.approx(0.75)
    assert a["success_held_out"] == 1.0
    assert a["success_oracle"] == pytest.approx(0.5)
    assert a["success_stochastic"] == 0.0
    assert a["return"] == pytest.approx(4.0)  # held-out return is not a trainable pair's
    assert b["success"] == 0.0 and b["success_held_out"] == 0.0 and b["success_oracle"] is None
    assert c["success"] == 1.0 and c["success_seen"] is None and c["success_held_out"] is None
    assert s["average_success"] == pytest.approx(0.25)  # mean of A (0.5) and B (0.0) only
    assert s["zero_shot_success"] == pytest.approx(0.5)  # held-out pairs of every group


def test_forgetting_is_best_earlier_minus_last_after_first_seen():
    def p(it, succ, shown=True):
        return fake_pass(it, [row("A", "e", "seen" if shown else "unseen", succ)], seen(*(["A"] if shown else [])))

    assert forgetting([p(1, 0.9)], "A") is None
    assert forgetting([p(0, 1.0, shown=False), p(1, 0.9)], "A") is None  # before A was shown: not counted
    passes = [p(0, 1.0, shown=False), p(1, 0.2), p(2, 0.8), p(3, 0.5)]
    assert forgetting(passes, "A") == pytest.approx(0.3)
    assert forgetting([p(1, 0.2), p(2, 0.6)], "A") == pytest.approx(-0.4)  # improved: negative forgetting
    assert forgetting(passes, "B") is None


def curve(points, task="A"):
    """Passes of ``task`` with (env steps on the group, success), oldest first."""
    return [fake_pass(i, [row(task, "e", "seen", s)], seen(task, steps={task: n})) for i, (n, s) in enumerate(points)]


def test_forward_transfer_trapezoid_rule_over_steps_on_the_group():
    run = curve([(0, 0.0), (100, 0.5), (200, 1.0)])
    # AUC over [0, 200]: 100 * (0 + 0.5) / 2 + 100 * (0.5 + 1) / 2 = 100 -> 0.5
    ref = curve([(100, 0.2), (300, 0.2)])
    # budget min(200, 300) = 200; the reference's first value from 0, its last held to 200: 0.2
    assert forward_transfer(run, "A", ref) == pytest.approx((0.5 - 0.2) / (1 - 0.2))
    # a budget cut by the run (100 steps): AUC 100 * 0.5 / 2 / 100 = 0.25 against 0.2
    assert forward_transfer(curve([(0, 0.0), (100, 0.5)]), "A", ref) == pytest.approx((0.25 - 0.2) / 0.8)
    # a group that recurs: two passes at the same steps on it (it was not trained between them,
    # success fell from 0.8 to 0.2); training resumes from the later value: 100 * 0.8 + 100 * (0.2 + 0.5) / 2
    recurring = curve([(100, 0.8), (100, 0.2), (200, 0.5)])
    assert forward_transfer(recurring, "A", curve([(200, 0.0)])) == pytest.approx(115 / 200)
    # reference = 1 (it solved the task from the start): no normalisation, plain difference
    perfect = curve([(100, 1.0), (200, 1.0)])
    assert forward_transfer(run, "A", perfect) == pytest.approx(0.5 - 1.0)
    assert forward_transfer(perfect, "A", perfect) == 0.0
    assert forward_transfer(run, "A", []) is None and forward_transfer([], "A", ref) is None


def test_continual_metrics_and_metric_row_keys():
    passes = [
        fake_pass(
            1, [row("A", "e", "seen", 1.0, oracle=1.0), row("B", "e", "unseen", 0.0)], seen("A", steps={"A": 100})
        ),
        fake_pass(
            2,
            [row("A", "e", "seen", 0.5, oracle=1.0), row("B", "e", "seen", 1.0), row("B", "h", "held_out", 0.25)],
            seen("A", "B", steps={"A": 100, "B": 100}),
        ),
    ]
    cl = continual_metrics(passes, {"A": curve([(100, 0.0)])})
    assert cl["passes"] == 2 and cl["iteration"] == 2
    assert cl["average_success"] == pytest.approx(0.75)
    assert cl["forgetting"] == {"A": pytest.approx(0.5), "B": None}  # B: one pass since it was shown
    assert cl["average_forgetting"] == pytest.approx(0.5)
    assert cl["zero_shot_success"] == 0.25
    r = metric_row(cl)
    assert set(r) == {
        "eval/average_success",
        "eval/zero_shot_success",
        "eval/average_forgetting",
        "eval/average_forward_transfer",
        "eval/success/A",
        "eval/success_worst/A",
        "eval/success_oracle/A",
        "eval/return/A",
        "eval/success/B",
        "eval/success_worst/B",
        "eval/success_held_out/B",
        "eval/return/B",
        "eval/forgetting/A",
        "eval/forward_transfer/A",
    }
    assert all(isinstance(v, float) for v in r.values())
    with pytest.raises(ValueError, match="no evaluation passes"):
        continual_metrics([])


def test_passes_table_gives_mean_over_trainable_and_worst_over_all_pairs_at_every_pass():
    from covers_dist.evaluation.report import passes_table

    first = {**fake_pass(1, [row("A", "e", "seen", 1.0), row("A", "r1", "held_out", 0.0)], seen("A")), "env_steps": 240_000}
    later = {
        **fake_pass(2, [row("A", "e", "seen", 0.5), row("A", "r1", "held_out", 1.0), row("B", "e", "seen", 0.25)], seen("A", "B")),
        "env_steps": 1_440_000,
    }
    md = passes_table([first, later], ["A", "B"])
    assert md.splitlines()[0] == "| group | 240k | 1.44M |"
    assert "| A | 1.00/0.00 | 0.50/0.50 |" in md  # the held-out pair counts for the worst, not the mean
    assert "| B | - | 0.25/0.25 |" in md  # not shown yet at the first pass


def test_worst_pair_and_groups_held_at_a_threshold_over_consecutive_passes():
    """The worst pair counts every (task, g), held-out and unseen ones too; a group is held when its
    worst pair meets the threshold at each of the last ``held`` passes, not just at some of them."""
    p1 = fake_pass(1, [row("A", "e", "seen", 1.0), row("A", "r", "held_out", 0.5), row("B", "e", "seen", 1.0)], seen("A", "B"))
    p2 = fake_pass(2, [row("A", "e", "seen", 1.0), row("A", "r", "held_out", 0.95), row("B", "e", "seen", 0.8)], seen("A", "B"))
    p3 = fake_pass(3, [row("A", "e", "seen", 0.9), row("A", "r", "held_out", 1.0), row("B", "e", "seen", 1.0),
                       {"task": "B", "g": "r", "status": "unseen", "results": {}}], seen("A", "B"))
    assert group_worst(p1, "A") == 0.5 and group_worst(p3, "B") == 1.0  # a pair that did not run is left out
    assert pass_summary(p2)["groups"]["A"]["success_worst"] == 0.95
    assert held_groups([p1, p2, p3], 0.9, 2) == ["A"]  # B fell to 0.8 at pass 2
    assert held_groups([p1, p2, p3], 0.9, 1) == ["A", "B"]
    assert held_groups([p1, p2, p3], 0.9, 3) == []  # A's held-out pair was at 0.5 at pass 1
    assert held_groups([p3], 0.9, 2) == []  # fewer passes than asked for
    assert held_groups([p1, p2, p3], 0.95, 2) == []  # A's 0.9 at pass 3
    with pytest.raises(ValueError, match="held=0"):
        held_groups([p1], 0.9, 0)


@pytest.mark.parametrize(
    "settings, stops",
    [
        ({"stop_at": 0.9, "held": 2, "stop_groups": "any"}, "A: greedy success >= 0.9 on every (task, g) at 2 passes"),
        ({"stop_at": 0.9, "held": 2, "stop_groups": "all"}, None),  # B not held
        ({"stop_at": 0.9, "held": 1, "stop_groups": "all"}, "A, B: greedy success >= 0.9"),
        ({"stop_at": None}, None),
    ],
)
def test_stop_reason_follows_eval_stop_at_and_stop_groups(tmp_path, settings, stops):
    cfg = tiny_cfg(tmp_path, "eval.every_iterations=1", *(f"eval.{k}={'null' if v is None else v}" for k, v in settings.items()))
    evaluation = runtime_evaluation.PeriodicEvaluation(cfg, tmp_path, background=False)
    evaluation.passes = [
        fake_pass(1, [row("A", "e", "seen", 1.0), row("B", "e", "seen", 0.5)], seen("A", "B")),
        fake_pass(2, [row("A", "e", "seen", 0.9), row("B", "e", "seen", 1.0)], seen("A", "B")),
    ]
    reason = evaluation.stop_reason()
    assert reason == stops if stops is None else reason.startswith(stops)


def test_read_passes_names_a_corrupt_line_and_keeps_the_newest_pass_per_iteration(tmp_path):
    log = tmp_path / "eval.jsonl"
    good = [json.dumps(fake_pass(i, [], {})) for i in (4, 2)]
    log.write_text("\n".join([good[0], "{not json", good[1]]) + "\n")
    with pytest.raises(ValueError, match=r"eval\.jsonl:2 is not valid JSON"):
        read_passes(tmp_path)
    log.write_text("\n".join([good[0], json.dumps({"iteration": 3}), good[1]]) + "\n")
    with pytest.raises(ValueError, match=r"eval\.jsonl:2 is not an evaluation pass"):
        read_passes(tmp_path)
    again = json.dumps({**fake_pass(4, [], {}), "source": "checkpoint"})
    log.write_text("\n".join([good[0], good[1], again, '{"iteration": 5, "pa']) + "\n")  # interrupted append
    passes = read_passes(tmp_path)
    assert [p["iteration"] for p in passes] == [2, 4] and passes[1]["source"] == "checkpoint"
    assert read_passes(tmp_path / "none") == []
    with pytest.raises(FileNotFoundError, match="covers-dist eval"):
        read_passes(tmp_path / "none", missing_ok=False)


# ---- the protocol ------------------------------------------------------------------------------------
def test_eval_seeds_are_deterministic_and_never_training_seeds():
    training = {episode_seed(seed, i) for seed in (0, 1) for i in range(5000)}
    ours = [eval_seed(seed, g, j, k) for seed in (0, 1) for g in range(3) for j in range(8) for k in range(16)]
    assert not training & set(ours)
    assert len(set(ours)) == len(ours)  # every (run seed, group, element, episode) its own initial state
    assert ours == [eval_seed(seed, g, j, k) for seed in (0, 1) for g in range(3) for j in range(8) for k in range(16)]


def test_eval_pairs_mark_held_out_seen_and_unseen_as_the_stream_does():
    stream = TaskStream(TASKS, "D4", 8, held_out=3, seed=0)
    held = set(stream.held_out_pairs)
    assert len(held) == 3
    for done in (0, 1, 8, 9, 24, 200):
        pairs = eval_pairs(stream, done)
        assert len(pairs) == 24 and len({p.key for p in pairs}) == 24
        scheduled = {stream.task_at(i).key for i in range(done)}
        assert {(p.task, p.g) for p in pairs if p.status == "held_out"} == held
        assert {(p.task, p.g) for p in pairs if p.status == "seen"} == scheduled
        for p in pairs:
            assert p.group_id == TASKS.index(p.task) and list(stream.group)[p.element_index].name == p.g
    assert {(p.task, p.g) for p in eval_pairs(stream, 9) if p.status == "seen"} == {
        stream.task_at(0).key,
        stream.task_at(8).key,
    }
    assert {p.task for p in eval_pairs(stream, 8, ["push"])} == {"push"}
    with pytest.raises(ValueError, match="nope"):
        eval_pairs(stream, 8, ["push", "nope"])


def test_oracle_policies_from_a_confusion_table():
    confusion = {"policies": [0, 1, 2], "groups": [0, 1, 2, 3], "counts": [[5, 0, 1, 2], [1, 0, 1, 2], [0, 0, 3, 0]]}
    # group 1 never trained: no oracle; group 3 is a tie between policies 0 and 1: the lower id
    assert oracle_policies(confusion) == {0: 0, 2: 2, 3: 0}
    assert oracle_policies({}) == {}


def test_plan_jobs_runs_a_policy_chosen_by_both_selections_once():
    a = EvalPair("reach", "e", 0, 0, "seen")
    b = EvalPair("push", "r", 1, 1, "unseen")
    c = EvalPair("avoid", "f", 2, 5, "held_out")
    jobs = plan_jobs([a, b, c], {a.key: 1, b.key: 0}, {0: 1, 1: 2}, run_seed=7, episodes=3)
    got = [(j.pair.key, j.policy_id, j.mode, j.selections) for j in jobs]
    assert got == [
        (a.key, 1, "greedy", ["agnostic", "oracle"]),
        (a.key, 1, "stochastic", ["agnostic", "oracle"]),
        (b.key, 0, "greedy", ["agnostic"]),
        (b.key, 0, "stochastic", ["agnostic"]),
        (b.key, 2, "greedy", ["oracle"]),
        (b.key, 2, "stochastic", ["oracle"]),
    ]  # c: no policy for its group and none chosen: nothing to run
    assert jobs[0].seeds == [eval_seed(7, 0, 0, k) for k in range(3)]
    # every element of a group runs its own instances: a group's figure rests on |G| x episodes states
    same_group = plan_jobs([a, EvalPair("reach", "r", 0, 1, "unseen")], {}, {0: 1}, run_seed=7, episodes=3)
    assert same_group[0].seeds == jobs[0].seeds
    assert same_group[2].seeds == [eval_seed(7, 0, 1, k) for k in range(3)]
    assert not set(same_group[2].seeds) & set(jobs[0].seeds)
    assert jobs[2].seeds == [eval_seed(7, 1, 1, k) for k in range(3)] != jobs[0].seeds
    outcomes = [{"success": [1.0, 0.0, 0.0], "return": [3.0, 0.0, 0.0], "state_key": ["s1", "s2", "s2"]}] * len(jobs)
    rows = pair_rows([a, b, c], jobs, outcomes, {}, {0: 1, 1: 2})
    assert set(rows[0]["results"]) == KEYS and rows[0]["results"]["greedy/oracle"]["success"] == pytest.approx(1 / 3)
    first = rows[0]["results"]["greedy/oracle"]
    assert (first["n"], first["successes"], first["distinct_initial_states"]) == (3, 1, 2)
    lo, hi = first["ci95"]
    assert 0.0 < lo < 1 / 3 < hi < 1.0
    assert set(rows[1]["results"]) == KEYS and rows[1]["results"]["greedy/oracle"]["policy_id"] == 2
    assert rows[2]["results"] == {} and rows[2]["oracle_policy"] is None


class FakeWorker:
    """Stands for a RolloutWorker: a frame per seed, success 1 only for policy 5."""

    def __init__(self):
        self.calls = []

    def eval_first_frames(self, items):
        self.calls.append(("frames", len(items)))
        return [{"image": np.zeros((len(s), 1)), "proprio": np.zeros((len(s), 1))} for _, s in items]

    def eval_jobs(self, jobs, weights_map):
        self.calls.append(("jobs", len(jobs)))
        return [
            {"success": [float(weights_map[j.policy_id][1] == "w5")] * len(j.seeds), "return": [0.0] * len(j.seeds)}
            for j in jobs
        ]


def test_run_evaluation_spreads_work_and_gives_a_new_policy_fresh_weights():
    pairs = [EvalPair("reach", "e", 0, 0, "seen"), EvalPair("push", "e", 1, 0, "unseen")]
    workers = [FakeWorker() for _ in range(3)]  # more workers than pairs: the idle one gets an empty list

    def choose(obs, groups):  # the pair's 2 episodes together, then each episode's own frame
        assert len(groups) == len(obs["image"]) in (1, 2)
        return {"policy_id": 0 if groups[0] == 0 else 5, "decision": "recall" if groups[0] == 0 else "new"}

    fresh = lambda pid: (-1, f"w{pid}")  # noqa: E731
    ev = run_evaluation(LocalExecutors(workers), pairs, choose, {0: 0}, {0: (1, "w0")}, 0, 2, new_policy=fresh)
    reach, push = ev["pairs"]
    assert reach["agnostic_policy"] == 0 and set(reach["results"]) == KEYS
    assert push["agnostic_policy"] == 5 and push["agnostic_decision"] == "new" and push["oracle_policy"] is None
    got = push["results"]["greedy/agnostic"]
    assert {k: got[k] for k in ("policy_id", "success", "return", "episodes", "n", "successes")} == {
        "policy_id": 5, "success": 1.0, "return": 0.0, "episodes": 2, "n": 2, "successes": 2,
    }  # fmt: skip
    assert got["distinct_initial_states"] is None  # these workers report no initial states
    assert ev["eval_episodes"] == 4 * 2
    # 2 pairs and 4 jobs dealt round-robin over 3 workers
    assert [w.calls for w in workers] == [
        [("frames", 1), ("jobs", 2)],
        [("frames", 1), ("jobs", 1)],
        [("frames", 0), ("jobs", 1)],
    ]
    # without new_policy, the pair whose choice would be a new policy gets no agnostic result
    ev = run_evaluation(LocalExecutors([FakeWorker()]), pairs, choose, {0: 0}, {0: (1, "w0")}, 0, 2)
    assert ev["pairs"][1]["results"] == {}
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        run_evaluation(LocalExecutors([FakeWorker()]), pairs, choose, {}, {}, 0, 0)


def test_agnostic_episodes_act_with_their_own_choice_and_the_disagreement_is_counted():
    """Each episode's own first frame picks its policy (the nearest one where its rule says
    ``new``); the pair-level choice is recorded, with the fraction of episodes that differ."""
    pairs = [EvalPair("reach", "e", 0, 0, "seen")]

    class Worker(FakeWorker):
        def eval_first_frames(self, items):
            return [{"image": np.arange(len(s), dtype=float)[:, None], "proprio": np.zeros((len(s), 1))} for _, s in items]

        def eval_jobs(self, jobs, weights_map):
            return [{"success": [float(j.policy_id == 0)] * len(j.seeds), "return": [1.0] * len(j.seeds)} for j in jobs]

    def choose(obs, groups):
        if len(obs["image"]) > 1:
            return {"policy_id": 0, "decision": "recall", "distances": {"0": 0.5, "1": 0.9}}
        if obs["image"][0, 0] == 2:  # episode 2 alone would start a new policy; policy 1 is the nearest
            return {"policy_id": 2, "decision": "new", "distances": {"0": 3.0, "1": 2.0}}
        return {"policy_id": int(obs["image"][0, 0] == 3), "decision": "recall", "distances": {"0": 0.5, "1": 0.9}}

    ev = run_evaluation(
        LocalExecutors([Worker()]), pairs, choose, {0: 0}, {0: (1, "w0"), 1: (1, "w1")}, 0, 4,
        modes=["greedy"], split="stop",
    )
    row = ev["pairs"][0]
    assert row["agnostic_policy"] == 0 and row["episode_policies"] == [0, 0, 1, 1]
    assert row["episode_choice_disagreement"] == 0.5 and ev["episode_choice_disagreement"] == 0.5
    got = row["results"]["greedy/agnostic"]
    assert got["policies"] == [0, 0, 1, 1] and got["success"] == 0.5 and got["n"] == 4
    assert row["results"]["greedy/oracle"]["success"] == 1.0 and "policies" not in row["results"]["greedy/oracle"]
    assert ev["split"] == "stop" and ev["seeds"]["reach|e"] == pair_seeds(0, pairs[0], 4, "stop")


def test_stop_and_report_splits_have_disjoint_initial_states():
    pair = EvalPair("reach", "r", 0, 1, "seen")
    stop, report = pair_seeds(3, pair, 64, "stop"), pair_seeds(3, pair, 64, "report")
    assert not set(stop) & set(report) and len(set(stop)) == 64
    assert report == [eval_seed(3, 0, 1, k) for k in range(64)]  # report seeds are the seeds of before
    with pytest.raises(ValueError, match="split must be one of"):
        eval_seed(3, 0, 1, 0, "train")


def timeless(record):
    return {k: v for k, v in record.items() if k not in ("time_unix", "wall_time_ms")}


def toy_frames(cfg, task, n):
    """``n`` first observations of ``task`` (identity element), as a bank takes them."""
    from covers_dist.envs import make_task
    from covers_dist.symmetry import GroupElement

    env = make_task(cfg.env, task, GroupElement.from_name("e"))
    obs = [env.reset(seed=s)[0] for s in range(n)]
    env.close()
    return {k: np.stack([o[k] for o in obs]) for k in ("image", "proprio")}


def test_ground_truth_what_if_with_several_frames_per_episode(tmp_path):
    """COVERS-GT with initial_frames=2: an evaluation pass sends one first frame per episode and one
    true group per frame; the bank, which counts 2 frames per episode, still gets the pair's group."""
    from covers_dist.runtime.clustering_service import ClusteringService

    cfg = tiny_cfg(tmp_path, "runtime.method=covers-gt", "clustering.initial_frames=2")
    service = ClusteringService(cfg)
    four = toy_frames(cfg, "push", 4)
    service.assign(0, four, [0, 1], [1, 1], {})
    frames = {k: v[:2] for k, v in four.items()}
    assert service.what_if(frames, [1, 1])["decision"] == "recall"
    assert service.what_if({k: v[:3] for k, v in four.items()}, [1, 1, 1])["policy_id"] == 0
    assert service.what_if(frames, [0, 0])["decision"] == "new"
    assert len(service.bank.history) == 1  # what-ifs change nothing


# ---- a serial training run with evaluation ------------------------------------------------------------
def test_training_writes_passes_every_two_iterations_and_at_the_end(runs):
    on, _ = runs
    passes = lines(on / "eval.jsonl")
    assert [(p["iteration"], p["source"]) for p in passes] == [(2, "training"), (3, "training")]
    stream = TaskStream(TASKS, "D4", 8, held_out=2, seed=0)
    episodes = lines(on / "episodes.jsonl")
    for ev in passes:
        assert ev["episodes"] == 8 * ev["iteration"] and ev["episodes_per_job"] == 2
        assert len(ev["pairs"]) == 16 and {r["task"] for r in ev["pairs"]} == {"reach", "push"}
        statuses = {(r["task"], r["g"]): r["status"] for r in ev["pairs"]}
        held = {k for k in stream.held_out_pairs if k[0] != "avoid"}
        assert {k for k, s in statuses.items() if s == "held_out"} == held
        scheduled = {stream.task_at(i).key for i in range(ev["episodes"])}
        assert {k for k, s in statuses.items() if s == "seen"} == {k for k in scheduled if k[0] != "avoid"}
        # progress per group: env steps on it and its first episode, from the episodes it trained on
        done = [e for e in episodes if e["episode_index"] < ev["episodes"]]
        assert sum(g["env_steps"] for g in ev["groups"].values()) == ev["env_steps"] == 25 * len(done)
        for task, info in ev["groups"].items():
            mine = [e["episode_index"] for e in done if e["task"] == task]
            assert info["first_episode"] == (min(mine) if mine else None)
        jobs = 0
        for r in ev["pairs"]:
            trained = ev["groups"][r["task"]]["first_episode"] is not None
            assert r["agnostic_policy"] is not None and (r["oracle_policy"] is not None) == trained
            keys = KEYS if trained else {"greedy/agnostic", "stochastic/agnostic"}
            assert set(r["results"]) == keys
            for key, res in r["results"].items():
                assert res["episodes"] == 2 and 0.0 <= res["success"] <= 1.0 and np.isfinite(res["return"])
                if key.endswith("agnostic"):  # each episode acted by its own choice
                    assert res.get("policies", [res["policy_id"]] * 2) == r["episode_policies"]
                else:
                    assert res["policy_id"] == r["oracle_policy"]
            # episodes run per mode: each (policy, episode) once, whichever selections chose it
            runs = {(q, i) for i, q in enumerate(r["episode_policies"])}
            runs |= {(r["oracle_policy"], i) for i in range(2)} if r["oracle_policy"] is not None else set()
            jobs += 2 * len(runs)
        assert ev["eval_episodes"] == jobs
    # every (pair, episode) starts from its own state: 16 pairs x 2 episodes, counted by fingerprint
    for ev in passes:
        assert ev["distinct_initial_states"] == 16 * 2
        for r in ev["pairs"]:
            for res in r["results"].values():
                assert res["n"] == 2 and res["distinct_initial_states"] == 2 and len(res["ci95"]) == 2
    metric_rows = lines(on / "metrics.jsonl")
    assert [r["iteration"] for r in metric_rows] == [1, 2, 3, 3]  # the last iteration again, with the final pass
    assert not any(k.startswith("eval/") for k in metric_rows[0])
    for r in (metric_rows[1], metric_rows[3]):
        assert {"eval/average_success", "eval/zero_shot_success", "eval/success/reach"} <= set(r)
    summary = pass_summary(passes[-1])
    assert metric_rows[3]["eval/average_success"] == pytest.approx(summary["average_success"])


def test_an_equivariant_policy_scores_the_same_on_every_transform_of_one_state(one_torch_thread):
    """Reset with the same seed, g.T is the exact transform of T: the one D4-equivariant network
    acting greedily gets the same success and return on every g, and every g's initial state has
    the same fingerprint (the evaluation's own seeds differ per g on purpose; this test does not)."""
    from covers_dist.config import load_config
    from covers_dist.evaluation.protocol import EvalJob
    from covers_dist.runtime.rollout import RolloutWorker

    cfg = load_config("configs/smoke.yaml", ["env.tasks=[reach, push]"])
    worker = RolloutWorker(cfg)
    weights = worker.model.get_weights()
    seeds = [11, 12, 13]
    try:
        for task in ("reach", "push"):
            jobs = [EvalJob(EvalPair(task, g.name, 0, j, "seen"), 0, "greedy", seeds) for j, g in enumerate(get_group("D4"))]
            out = worker.eval_jobs(jobs, {0: (0, weights)})
            for res in out[1:]:
                assert res["success"] == out[0]["success"]
                assert res["return"] == pytest.approx(out[0]["return"], abs=1e-3)
                assert res["state_key"] == out[0]["state_key"]
            assert len(set(out[0]["state_key"])) == len(seeds)
    finally:
        worker.close()


def test_evaluation_does_not_change_training(runs):
    on, off = runs
    assert not (off / "eval.jsonl").exists()
    cols = ("iteration", "env_steps", "policy_id", "num_policies", "ari", "ppo/policy_loss", "ppo/value_loss")
    rows_on = [r for r in lines(on / "metrics.jsonl") if "eval/average_success" not in r or r["iteration"] != 3]
    assert [[r.get(c) for c in cols] for r in rows_on] == [[r.get(c) for c in cols] for r in lines(off / "metrics.jsonl")]
    ckpt_on, ckpt_off = on / "checkpoints" / "ckpt-000003", off / "checkpoints" / "ckpt-000003"
    # the driver state, random-number generator states included, is the same (but for the timing
    # of the update in flight)
    states = [json.loads((c / "driver.json").read_text()) for c in (ckpt_on, ckpt_off)]
    for state in states:
        for key in ("ppo/update_time_s", "ppo/samples_per_s"):
            state.get("pending_update", {}).get("stats", {}).pop(key, None)
    assert states[0] == states[1]
    learners = sorted(p.name for p in (ckpt_off / "learners").iterdir())
    assert learners == sorted(p.name for p in (ckpt_on / "learners").iterdir())
    for name in learners:  # policy-N.pt: learner states; sampling-N.pt: weights (pipelined loop)
        a = torch.load(ckpt_on / "learners" / name, weights_only=False)
        b = torch.load(ckpt_off / "learners" / name, weights_only=False)
        if name.startswith("policy-"):
            a, b = a["ppo"]["model"], b["ppo"]["model"]
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ---- covers-dist eval / report ------------------------------------------------------------------------
def eval_json(capsys, run_dir, *args):
    capsys.readouterr()
    assert main(["eval", str(run_dir), "--no-write", "--json", *args]) == 0
    return json.loads(capsys.readouterr().out)


def test_eval_command_is_read_only_deterministic_and_matches_the_training_pass(runs, tmp_path, capsys):
    on, _ = runs
    run = tmp_path / "run"
    shutil.copytree(on, run)
    before = snapshot(run)
    # the training passes' episodes: their split and count
    first = eval_json(capsys, run, "--tasks", "reach", "--episodes", "2", "--split", "stop")
    assert snapshot(run) == before  # --no-write: nothing at all
    assert first["pass"]["iteration"] == 3 and first["pass"]["source"] == "checkpoint ckpt-000003"
    assert first["metrics"]["passes"] == 2  # the training's pass at iteration 2, then this one
    # the same bank, weights, pairs and seeds as the training's final pass: the same results
    final = {(r["task"], r["g"]): r for r in lines(on / "eval.jsonl")[-1]["pairs"]}
    for r in first["pass"]["pairs"]:
        t = final[(r["task"], r["g"])]
        assert r["status"] == t["status"] and r["results"] == t["results"]
        assert (r["agnostic_policy"], r["agnostic_decision"], r["oracle_policy"]) == (
            t["agnostic_policy"],
            t["agnostic_decision"],
            t["oracle_policy"],
        )
        assert r["agnostic_distance"] == pytest.approx(t["agnostic_distance"], rel=1e-5)
    assert first["pass"]["split"] == "stop" and first["pass"]["seeds"] == {
        k: v for k, v in lines(on / "eval.jsonl")[-1]["seeds"].items() if k.startswith("reach|")
    }
    # the report split (the default): initial states the training passes never saw
    report = eval_json(capsys, run, "--tasks", "reach", "--episodes", "2")["pass"]
    assert report["split"] == "report"
    assert not {s for v in report["seeds"].values() for s in v} & {s for v in first["pass"]["seeds"].values() for s in v}
    # again, written this time: the same pass, appended to eval.jsonl and to nothing else
    assert main(["eval", str(run), "--tasks", "reach", "--episodes", "2", "--split", "stop"]) == 0
    out = capsys.readouterr().out
    assert "| reach |" in out and "average success" in out and "appended to" in out
    after = snapshot(run)
    assert {k for k in set(before) | set(after) if before.get(k) != after.get(k)} == {"eval.jsonl"}
    passes = lines(run / "eval.jsonl")
    assert len(passes) == 3 and passes[-1]["pairs"] == first["pass"]["pairs"]
    assert read_passes(run)[-1]["source"] == "checkpoint ckpt-000003"  # the newest pass of iteration 3
    assert main(["report", str(run)]) == 0
    report = (run / "report.md").read_text()
    assert "## Per task group" in report and "| reach |" in report
    assert "calibrated rule's tail" not in report  # the threshold rule: no permutation tests to read
    # every pass of the run, one column each: mean over the trainable pairs / worst over all
    every = report.split("## Every pass", 1)[1].split("## Every (task, g)", 1)[0]
    from covers_dist.evaluation.report import _f

    cells = [f"{_f(group_success(ev, 'reach'))}/{_f(group_worst(ev, 'reach'))}" for ev in read_passes(run)]
    assert "| reach | " + " | ".join(cells) + " |" in every and "| push |" in every


def test_eval_and_report_bad_input_are_clear_errors(runs, tmp_path, capsys):
    on, off = runs
    with pytest.raises(SystemExit, match="does not exist"):
        main(["eval", str(tmp_path / "missing")])
    assert not (tmp_path / "missing").exists()
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(on / "config.yaml", bare / "config.yaml")
    with pytest.raises(SystemExit, match="no valid checkpoint"):
        main(["eval", str(bare)])
    assert sorted(p.name for p in bare.iterdir()) == ["config.yaml"]
    before = snapshot(on)
    with pytest.raises(SystemExit, match=r"\['nope'\] were never part of this run"):
        main(["eval", str(on), "--tasks", "reach,nope"])
    with pytest.raises(SystemExit, match="--episodes must be >= 1, got 0"):
        main(["eval", str(on), "--episodes", "0"])
    assert snapshot(on) == before
    with pytest.raises(SystemExit, match=r"eval\.jsonl does not exist: run `covers-dist eval"):
        main(["report", str(off)])
    assert not (off / "report.md").exists()


def test_report_of_a_calibrated_run_ends_with_the_rules_tail(tmp_path, one_torch_thread):
    """Under the calibrated rule the page ends with the tail of the run's own-policy tests, the
    counts of ``calibration_tail`` over the saved bank's records."""
    from covers_dist.clustering import calibration_tail
    from covers_dist.runtime.saved_run import load_saved_run

    run = tmp_path / "cal"
    # 12 assignments; N = max(20 samples, 1 / 0.05 - 1) = 20 draws, so the rows are k = 10 and 21
    train(run, "clustering.rule=calibrated", "clustering.false_split_rate=0.05", "clustering.calibration_samples=20",
          "runtime.total_env_steps=2400", "eval.every_iterations=0")
    assert main(["eval", str(run), "--episodes", "1", "--tasks", "reach", "--modes", "greedy",
                 "--selections", "agnostic"]) == 0
    assert main(["report", str(run)]) == 0
    report = (run / "report.md").read_text()
    tail = calibration_tail(load_saved_run(run, log=lambda *_: None).service.bank.history)
    assert tail["tests"] >= 3 and tail["labelled"] and [r["k"] for r in tail["rows"]] == [10, 21]
    section = report.split("## The calibrated rule's tail", 1)[1]
    assert "(false-split rate 0.05, N = 20 draws)" in section
    assert f"{tail['tests']} tests of a batch's own policy ({tail['skipped']} left out" in section
    for row in tail["rows"]:
        assert f"| {row['k']} | {row['count']} | {row['expected']:.2f} |" in section


def test_what_if_restricted_to_the_passes_policies(runs):
    """A pass beside training on Ray compares only with the policies it has weights for: the bank may
    already hold a policy whose weights the driver has not published yet."""
    from covers_dist.runtime.saved_run import load_saved_run

    on, _ = runs
    service = load_saved_run(on, log=lambda *_: None).service
    # how many policies the tiny run makes depends on the CPU's float rounding (2 or 3 seen): use them all
    ids = list(service.bank.policy_ids)
    assert len(ids) >= 2 and ids[0] == 0, ids
    last = ids[-1]
    frames = toy_frames(service.cfg, "reach", 2)
    every = service.what_if(frames, [0, 0])
    assert set(map(int, every["distances"])) == set(ids)
    assert timeless(service.what_if(frames, [0, 0], ids)) == timeless(every)
    service.models.pop(last)  # an entry without weights, as between the bank's `assign` and the driver's publish
    with pytest.raises(LookupError, match=f"no weights received yet for policy {last}"):
        service.what_if(frames, [0, 0])
    only = service.what_if(frames, [0, 0], [0])
    assert set(map(int, only["distances"])) == {0}
    assert only["distances"] == {k: v for k, v in every["distances"].items() if int(k) == 0}
    assert service.bank.policy_ids == ids  # the bank is as it was
    with pytest.raises(LookupError, match="none of the policies"):
        service.what_if(frames, [0, 0], [7])


def test_background_pass_still_running_at_the_end_is_followed_by_a_final_pass(tmp_path, monkeypatch, one_torch_thread):
    """The Ray path's background thread, here in one process: the pass started at iteration 1 is still
    running when training ends at iteration 2; the final pass evaluates iteration 2 all the same."""
    import threading

    release = threading.Event()
    real = runtime_evaluation.evaluation_pass
    calls = []

    def slow_pass(*args, **kwargs):
        calls.append(args[7]["iteration"])
        if len(calls) == 1:
            assert release.wait(120)
        return real(*args, **kwargs)

    monkeypatch.setattr(runtime_evaluation, "evaluation_pass", slow_pass)
    cfg = tiny_cfg(
        tmp_path, "runtime.total_env_steps=400", "eval.every_iterations=1", "eval.tasks=[reach]", "eval.modes=[greedy]",
        "eval.episodes=1",
    )
    trainer = Trainer(cfg, log=lambda *_: None)
    trainer.evaluation.background = True
    collect = trainer.evaluation.collect

    def collect_releasing(wait=False):
        if wait:
            release.set()
        return collect(wait)

    trainer.evaluation.collect = collect_releasing
    spied = []
    call = trainer.backend.call_clustering

    def spy(method, *args):
        if method == "what_if":
            spied.append(args[2])
        return call(method, *args)

    trainer.backend.call_clustering = spy
    assert trainer.run()["status"] == "finished"
    trainer.close()
    assert calls == [1, 2]  # iteration 2's due pass was skipped (one at a time); the final pass ran
    assert [p["iteration"] for p in lines(tmp_path / "eval.jsonl")] == [1, 2]
    # each pass compares with the policies it had weights for when it started
    published = json.loads((tmp_path / "checkpoints" / "ckpt-000002" / "driver.json").read_text())["policies"]
    # (per pass: every pair's episodes together, then each episode's own frames)
    per_pass = len(spied) // 2
    assert per_pass > 8 and spied == [[0]] * per_pass + [published] * per_pass
    rows = lines(tmp_path / "metrics.jsonl")
    assert rows[-1]["iteration"] == 2 and "eval/success/reach" in rows[-1]


def test_a_background_pass_that_ends_just_before_the_next_starts_is_still_collected(tmp_path):
    """On Ray a pass runs in a thread and is collected at the next iteration; when it ends just
    before the next pass is due, starting that pass must not drop it."""
    cfg = tiny_cfg(tmp_path, "eval.every_iterations=1")
    evaluation = runtime_evaluation.PeriodicEvaluation(cfg, tmp_path, background=True, log=lambda *_: None)

    def make(iteration):
        ev = fake_pass(iteration, [row("A", "e", "seen", iteration / 10)], seen("A"))
        return lambda: {**ev, "eval_episodes": 1, "time_s": {"total": 0.0}}

    evaluation.start(1, make(1))
    evaluation._thread.join()  # pass 1 done, not collected yet
    evaluation.start(2, make(2))
    metrics = evaluation.collect(wait=True)
    assert [p["iteration"] for p in lines(tmp_path / "eval.jsonl")] == [1, 2]
    assert metrics["eval/success/A"] == pytest.approx(0.2)  # the newest pass's figures
    assert evaluation.collect() == {}


def test_training_stops_once_a_group_is_held_and_at_the_time_limit(tmp_path, monkeypatch, one_torch_thread):
    """The driver's early stops on real serial runs. Toy groups do not reach 0.9 in a few iterations,
    so the passes' figures for reach are set to 1.0 from iteration 3 on: the stop, not learning, is
    under test. Held at 2 passes means passes 3 and 4; push never is, and stop_groups=any suffices."""
    real = runtime_evaluation.evaluation_pass

    def reach_solved_from_iteration_3(*args, **kwargs):
        ev = real(*args, **kwargs)
        for r in ev["pairs"]:
            if r["task"] == "reach" and ev["iteration"] >= 3:
                for res in r["results"].values():
                    res["success"] = 1.0
        return ev

    monkeypatch.setattr(runtime_evaluation, "evaluation_pass", reach_solved_from_iteration_3)
    quick = ["eval.tasks=[reach,push]", "eval.modes=[greedy]", "eval.selections=[agnostic]", "eval.episodes=1"]
    logs = []
    cfg = tiny_cfg(
        tmp_path / "held", "runtime.total_env_steps=2000", "eval.every_iterations=1", "eval.stop_at=0.9",
        "eval.stop_groups=any", *quick,
    )
    trainer = Trainer(cfg, log=logs.append)
    result = trainer.run()
    trainer.close()
    assert result["status"] == "finished" and result["row"]["env_steps"] == 800
    assert result["stopped_early"].startswith("reach: greedy success >= 0.9 on every (task, g) at 2 passes in a row")
    assert any(line.startswith("stopping at 800 env steps: reach:") for line in logs)
    assert [p["iteration"] for p in lines(tmp_path / "held" / "eval.jsonl")] == [1, 2, 3, 4]  # no extra final pass
    assert (tmp_path / "held" / "checkpoints" / "ckpt-000004").is_dir()
    resumed = Trainer(cfg, resume=True, log=lambda *_: None)  # met already: stops before any iteration
    result = resumed.run()
    resumed.close()
    assert result["stopped_early"].startswith("reach: greedy success >= 0.9") and result["row"] == {}
    assert [p["iteration"] for p in lines(tmp_path / "held" / "eval.jsonl")] == [1, 2, 3, 4]

    cfg = tiny_cfg(tmp_path / "timed", "runtime.time_limit_minutes=1e-6", "eval.every_iterations=5", *quick)
    trainer = Trainer(cfg, log=lambda *_: None)
    result = trainer.run()
    trainer.close()
    assert result["status"] == "finished" and result["row"]["env_steps"] == 200
    assert result["stopped_early"] == "the time limit of 1e-06 min (runtime.time_limit_minutes)"
    assert [p["iteration"] for p in lines(tmp_path / "timed" / "eval.jsonl")] == [1]  # the final pass still runs


# ---- Ray ---------------------------------------------------------------------------------------------
def test_ray_evaluation_executors_give_the_local_pass(runs, ray_local):
    import dataclasses

    from covers_dist.runtime.backends import RayEvalExecutors
    from covers_dist.runtime.evaluation import evaluation_pass
    from covers_dist.runtime.saved_run import load_saved_run

    on, _ = runs
    saved = load_saved_run(on, log=lambda *_: None)
    cfg = dataclasses.replace(saved.cfg, eval=dataclasses.replace(saved.cfg.eval, modes=["greedy"]))
    stream = TaskStream.from_config(cfg.env, cfg.seed)
    info = {"iteration": saved.driver["iteration"], "groups": saved.driver["groups"]}
    confusion = saved.service.metrics()["confusion"]

    executors = RayEvalExecutors(dataclasses.replace(cfg, runtime=dataclasses.replace(cfg.runtime, serial=False)))
    try:
        remote = evaluation_pass(
            cfg, executors, stream, saved.driver["next_episode"], lambda o, g: saved.service.what_if(o, g),
            confusion, saved.weights_map, info, tasks=["push"],
        )
    finally:
        executors.close()
    # the training's final pass ran on a local executor with the same bank, weights and seeds
    local = {(r["task"], r["g"]): r for r in lines(on / "eval.jsonl")[-1]["pairs"]}
    assert len(remote["pairs"]) == 8 and remote["eval_episodes"] > 0
    for r in remote["pairs"]:
        t = local[(r["task"], r["g"])]
        assert set(r["results"]) == {"greedy/agnostic", "greedy/oracle"}
        assert r["results"] == {k: v for k, v in t["results"].items() if k.startswith("greedy/")}
        assert [r[k] for k in ("agnostic_policy", "oracle_policy", "status")] == [
            t[k] for k in ("agnostic_policy", "oracle_policy", "status")
        ]


# ---- methods side by side (`covers-dist compare`) ------------------------------------------------
def test_compare_puts_methods_side_by_side_and_refuses_unlike_runs(runs, equi_run, tmp_path, capsys):
    import dataclasses

    from covers_dist.commands.compare import load_runs
    from covers_dist.evaluation.compare import check_comparable

    on, off = runs
    equi = equi_run
    before = snapshot(on), snapshot(equi)
    out = tmp_path / "cmp"
    capsys.readouterr()
    assert main(["compare", str(on), str(equi), "--out", str(out), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert (snapshot(on), snapshot(equi)) == before  # read-only
    assert [r["label"] for r in data["runs"]] == ["covers", "equi"]
    held = sorted([r["task"], r["g"]] for r in read_passes(on)[-1]["pairs"] if r["status"] == "held_out")
    assert data["tasks"] == TASKS and data["held_out"] == held and held
    for r, run_dir in zip(data["runs"], (on, equi)):
        cl = continual_metrics(read_passes(run_dir))  # each row is the run's own metrics, not recomputed otherwise
        assert r["env_steps"] == cl["env_steps"] == 600 and r["passes"] == cl["passes"] == 2
        assert r["success"] == {t: g["success"] for t, g in cl["groups"].items()}
        assert r["average_success"] == cl["average_success"]
        assert r["zero_shot_success"] == cl["zero_shot_success"]
    assert data["runs"][1]["policies"] == 1 and data["runs"][0]["policies"] >= 2  # equi: one policy for all
    md = (out / "compare.md").read_text()
    assert "| covers | 0 | 600 |" in md and "| equi | 0 | 600 |" in md and "| 1 | n/a (one policy) |" in md
    assert (out / "compare_success.png").stat().st_size > 10_000
    # 3 segments of 3 tasks: no group came back, so no re-entry table; the critic's fit per group
    # from the real logs (sequential runs: each row reports its own batch's update)
    assert [r["reentry"] for r in data["runs"]] == [None, None] and "Across the gaps" not in md
    from covers_dist.evaluation.reentry import value_fit

    for r, run_dir in zip(data["runs"], (on, equi)):
        assert r["value_fit"] == value_fit(lines(run_dir / "metrics.jsonl"), lines(run_dir / "episodes.jsonl"), lag=0)
        assert sum(f["updates"] for f in r["value_fit"].values()) >= 2
    assert "## The critic's fit per group" in md
    # the same run twice, a run without passes, a missing directory: clear errors, nothing written
    for args, match in (
        ([str(on), str(on)], "is given twice"),
        ([str(on), str(off)], r"eval\.jsonl does not exist"),
        ([str(tmp_path / "nope")], "does not exist"),
        ([str(on), "--reentry-window", "0"], "--reentry-window must be >= 1"),
    ):
        with pytest.raises(SystemExit, match=match):
            main(["compare", *args, "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()
    # runs of different streams are refused, naming the field
    a, b = load_runs([on, equi])
    check_comparable([a, b])
    with pytest.raises(ValueError, match="max_episode_steps is 30 there and 25 here"):
        check_comparable([a, dataclasses.replace(b, max_episode_steps=30)])
    pairs = [dict(r, status="held_out") if r["status"] == "seen" else r for r in b.passes[-1]["pairs"]]
    with pytest.raises(ValueError, match="held_out is"):
        check_comparable([a, dataclasses.replace(b, passes=[{**b.passes[-1], "pairs": pairs}])])


def test_compare_across_seeds_averages_each_method_over_its_seeds(runs, equi_run, tmp_path, capsys):
    """Seeds hold out different pairs: a plain compare refuses them and points at --across-seeds,
    which keeps each run's own held-out pairs and adds mean +- std per method over its seeds."""
    import shutil

    on, _ = runs
    equi = equi_run
    s1 = tmp_path / "covers-s1"
    train(s1, "seed=1", "eval.every_iterations=2", "eval.tasks=[reach,push]")
    held = {d: sorted([r["task"], r["g"]] for r in read_passes(d)[-1]["pairs"] if r["status"] == "held_out") for d in (on, s1)}
    assert held[on] != held[s1]
    with pytest.raises(SystemExit, match=r"held_out is .*--across-seeds"):
        main(["compare", str(on), str(s1), "--out", str(tmp_path / "plain")])
    capsys.readouterr()
    out = tmp_path / "cmp"
    assert main(["compare", str(on), str(equi), str(s1), "--across-seeds", "--out", str(out), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["held_out"] is None
    assert [r["held_out"] for r in data["runs"]] == [held[on], held[on], held[s1]]
    assert [m["method"] for m in data["methods"]] == ["covers", "equi"]
    # a method with several runs names each by its seed, in the tables and the figure's legend
    assert [r["label"] for r in data["runs"]] == ["covers seed 0", "equi", "covers seed 1"]
    covers, eq = data["methods"]
    assert covers["seeds"] == [0, 1] and eq["seeds"] == [0]
    rows = [r for r in data["runs"] if r["method"] == "covers"]
    for key in ("average_success", "zero_shot_success", "env_steps"):
        values = [r[key] for r in rows]
        assert covers[key]["mean"] == pytest.approx(np.mean(values))
        assert covers[key]["std"] == pytest.approx(np.std(values, ddof=1))
        assert covers[key]["n"] == 2
    for t in TASKS:
        got = [r["success"].get(t) for r in rows if r["success"].get(t) is not None]
        assert (covers["success"][t] or {}).get("n", 0) == len(got)
    assert eq["average_success"]["std"] == 0.0 and eq["policies"]["mean"] == 1
    md = (out / "compare.md").read_text()
    assert "## Per method, mean +- standard deviation over seeds" in md and "| covers | 0, 1 |" in md
    assert "| equi | 0 |" in md and "n/a (one policy)" in md and "held-out pairs per run" in md
    assert "| covers seed 1 | 1 |" in md
    # one method twice with one seed would count that seed twice: refused, nothing written
    twin = tmp_path / "covers-again"
    shutil.copytree(on, twin)
    with pytest.raises(SystemExit, match="both covers with seed 0"):
        main(["compare", str(on), str(twin), "--across-seeds", "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()


def test_ppo_update_figure_draws_the_update_statistics_of_real_runs(runs, tmp_path):
    from covers_dist.commands.plot import PPO_PANELS, ppo_update_figure

    on, off = runs
    rows = [m for m in lines(on / "metrics.jsonl") if "ppo/approx_kl" in m]
    assert rows
    for m in rows:  # every statistic the figure draws is logged by the learner
        for key, _, _ in PPO_PANELS:
            assert key in m, key
        assert 0.0 <= m["ppo/mean_out_of_box"] <= 1.0
    path = ppo_update_figure({"on": on, "off": off}, tmp_path / "ppo.png", window=2)
    assert path.stat().st_size > 10_000
