"""Faults change nothing: a run whose workers, learners, clustering actor, HTTP service and driver
are killed at random ends where the clean run ends; so does a run that loses a node. And the faults
must happen: a run without them fails the verdict."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from covers_dist.bench.chaos import KINDS, STATE_PARTS, TARGET_KILLS, compare, failures, final_state, max_abs_diff

ROOT = Path(__file__).resolve().parents[1]

# a short stream: 400 env steps per iteration, learners on both sides of a kill
SHORT = ["runtime.checkpoint_every=2", "ppo.epochs=2"]


def _chaos(*args, timeout=1500):
    """``covers-dist bench chaos --json`` in its own process (it starts its own Ray instances)."""
    cmd = [sys.executable, "-m", "covers_dist", "bench", "chaos", "--json", *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    lines = done.stdout.strip().splitlines()
    # exit 1 with a report: the runs differ (the asserts below say how); without one: the bench failed
    assert done.returncode in (0, 1) and lines, f"exit {done.returncode}; stderr:\n{done.stderr[-4000:]}"
    report = json.loads(lines[-1])
    assert done.returncode == (0 if report["verdict"] else 1), (done.returncode, report["failures"])
    return report, done.stderr


def _sets(*overrides):
    return [x for o in (*SHORT, *overrides) for x in ("--set", o)]


def _assert_equal_to_clean(report):
    c = report["comparison"]
    assert c["assignments_identical"], c
    assert c["assigned_exactly_once"] and c["logged_exactly_once"], c
    assert c["logged_doubles"] == 0 and c["logged_missing"] == 0
    assert c["weights_identical"] and c["weights_max_abs_diff"] == 0.0, c
    assert c["state_identical"] and c["state_differences"] == {}, c["state_differences"]
    assert report["equal_to_clean"]


def _assert_passed(report):
    """Equal to the clean run and every fault happened: the verdict holds."""
    _assert_equal_to_clean(report)
    assert report["failures"] == [] and report["verdict"], report["failures"]


def test_compare_sees_a_changed_assignment_a_double_and_a_changed_weight():
    import torch

    clean = {
        "assignments": [(0, "new"), (0, "recall")],
        "assigned_episodes": [0, 1, 2, 3],
        "logged_episodes": [0, 1, 2, 3],
        "weights": {0: {"w": torch.zeros(3)}},
    }
    assert compare(clean, clean)["weights_identical"] and compare(clean, clean)["logged_exactly_once"]
    other = {**clean, "assignments": [(0, "new"), (1, "new")], "logged_episodes": [0, 1, 1, 2, 3],
             "weights": {0: {"w": torch.tensor([0.0, 0.5, 0.0])}}}  # fmt: skip
    c = compare(clean, other)
    assert not c["assignments_identical"] and not c["logged_exactly_once"] and c["logged_doubles"] == 1
    assert not c["weights_identical"] and c["weights_max_abs_diff"] == 0.5


def test_compare_sees_a_difference_in_every_part_of_the_whole_state(tiny_serial_run):
    """A real run's final state against itself is identical; one changed value anywhere (an Adam
    moment, a version, a driver counter, an RNG state, a bank buffer, a history record, a row of
    metrics.jsonl or eval.jsonl) fails the verdict with its path; wall-clock fields do not count."""
    import copy

    import numpy as np

    state = final_state(tiny_serial_run[2])
    assert set(STATE_PARTS) <= set(state) and compare(state, copy.deepcopy(state))["state_identical"]
    ppo = state["learners"]["policy-0"]["ppo"]
    moment_key = next(k for k in ppo["optimizer"]["state"][0] if k.startswith("exp_avg"))

    def moment(s):
        s["learners"]["policy-0"]["ppo"]["optimizer"]["state"][0][moment_key] += 1.0

    def buffer(s):
        key = next(iter(s["bank"]["buffers"]))
        s["bank"]["buffers"][key] = np.array(s["bank"]["buffers"][key], copy=True)
        s["bank"]["buffers"][key].flat[0] += 1

    changes = {
        "learners": [moment, lambda s: s["learners"]["policy-0"].update(version=s["learners"]["policy-0"]["version"] + 1)],
        "driver": [lambda s: s["driver"].update(env_steps=s["driver"]["env_steps"] + 1),
                   lambda s: s["driver"]["stream"].update(episode=-1)],
        "bank": [buffer, lambda s: s["bank"]["state"]["history"][0].update(decision="recall")],
        "metrics": [lambda s: s["metrics"][-1].update(iteration=99)],
    }  # fmt: skip
    for part, edits in changes.items():
        for edit in edits:
            other = copy.deepcopy(state)
            edit(other)
            c = compare(state, other)
            assert not c["state_identical"] and list(c["state_differences"]) == [part], (part, c["state_differences"])
            assert any(f"the {part}" in f or part in f for f in failures({"comparison": c})), part
    other = copy.deepcopy(state)
    other["eval"] = [*other["eval"], {"iteration": 5}]
    assert list(compare(state, other)["state_differences"]) == ["eval"]
    from covers_dist.bench.chaos import stable  # wall-clock fields are left out of every part

    assert "wall_time" not in state["metrics"][-1] and "time/sample" not in state["metrics"][-1]
    assert "wall_time" not in stable({"wall_time": 1.0, "time/sample": 2.0, "ppo/samples_per_s": 3.0, "a": 1})
    assert stable({"x": [{"time_unix": 1, "b": 2}]}) == {"x": [{"b": 2}]}


def test_max_abs_diff_does_not_hide_a_nan_or_an_unmatched_inf():
    import torch

    a = torch.tensor([0.0, 1.0, 2.0])
    assert max_abs_diff(a, a.clone()) == 0.0
    nan = torch.tensor([0.0, float("nan"), 2.0])
    assert math.isnan(max_abs_diff(a, nan)) and math.isnan(max_abs_diff(nan, a))
    assert math.isnan(max_abs_diff(nan, nan.clone()))  # NaN in both: still not equal
    assert max(0.0, float("nan")) == 0.0  # what a running max() does with it
    inf = torch.tensor([0.0, float("inf"), 2.0])
    assert max_abs_diff(inf, inf.clone()) == 0.0  # the same inf in both: equal
    assert max_abs_diff(a, inf) == math.inf and max_abs_diff(inf, -inf) == math.inf
    assert max_abs_diff(a, torch.zeros(4)) == math.inf  # another shape


def test_compare_fails_on_a_nan_in_either_run():
    import torch

    clean = {
        "assignments": [(0, "new")],
        "assigned_episodes": [0, 1],
        "logged_episodes": [0, 1],
        "weights": {0: {"a": torch.zeros(3), "b": torch.ones(2)}},
    }
    # the NaN tensor comes first: a running max() over (NaN, 0.0) would have reported 0.0
    for where in ("chaos", "clean"):
        bad = {**clean, "weights": {0: {"a": torch.tensor([0.0, float("nan"), 0.0]), "b": torch.ones(2)}}}
        c = compare(bad, clean) if where == "clean" else compare(clean, bad)
        assert not c["weights_identical"], where
        assert math.isnan(c["weights_max_abs_diff"]) and c["weights_with_nan"] == ["0/a"], where
        report = {"comparison": c}
        assert any("NaN" in f for f in failures(report)), where
    # a parameter missing from one policy is a difference too (not a KeyError)
    c = compare(clean, {**clean, "weights": {0: {"a": torch.zeros(3)}}})
    assert not c["weights_identical"] and c["weights_max_abs_diff"] is None


def test_the_verdict_needs_every_kind_killed_and_the_node_removed():
    import torch

    state = {"assignments": [(0, "new")], "assigned_episodes": [0], "logged_episodes": [0],
             "weights": {0: {"w": torch.zeros(2)}}}  # fmt: skip
    equal = compare(state, state)
    every = {k: 1 for k in KINDS}
    assert failures({"comparison": equal, "kills": every}, set(KINDS)) == []
    (reason,) = failures({"comparison": equal, "kills": {**every, "learner": 0, "api": 0}}, set(KINDS))
    assert "no learner / api was killed" in reason
    # only the kinds asked for are needed
    assert failures({"comparison": equal, "kills": {"worker": 2}}, {"worker"}) == []
    (reason,) = failures({"comparison": equal, "kills": {"worker": 0}}, {"worker"})
    assert "no worker was killed" in reason
    lost = {"lost": "workers", "lose_after": 3, "node_removed": False}
    (reason,) = failures({"comparison": equal, "node_loss": lost})
    assert "not removed" in reason and "--lose-after 3" in reason
    assert failures({"comparison": equal, "node_loss": {**lost, "node_removed": True}}) == []


def test_bad_chaos_arguments_are_refused_with_a_message(tmp_path, capsys):
    """Usage errors, exit status 2, before anything runs (no run directory, no Ray); in this process
    (`covers-dist`'s main), as the console script calls it."""
    from covers_dist.cli import main

    steps = ["--set", "runtime.total_env_steps=4000"]  # 10 iterations of 16 episodes of 25 steps
    for args, words in (
        (["--interval", "5,1"], ["MIN <= MAX"]),
        (["--interval", "x"], ["MIN,MAX"]),
        (["--kinds", "worker,gpu"], ["--kinds"]),
        (["--max-kills", "3"], ["--max-kills 3", f"{len(KINDS)} kinds"]),  # cannot kill each kind once
        (["--node-loss", "workers", "--lose-after", "10", *steps], ["--lose-after 10", "10 iterations", "1 to 9"]),
        (["--node-loss", "learners", "--lose-after", "400", *steps], ["--lose-after 400", "10 iterations"]),
        (["--node-loss", "workers", "--lose-after", "0", *steps], ["--lose-after 0", "1 to 9"]),
    ):
        out = tmp_path / "out"
        with pytest.raises(SystemExit) as exc:
            main(["bench", "chaos", "--config", str(ROOT / "configs" / "smoke.yaml"), "--out", str(out), *args])
        done = capsys.readouterr()
        assert exc.value.code == 2, (args, exc.value.code, done.err[-2000:])
        assert all(w in done.err for w in words), (args, done.err[-2000:])
        assert not out.exists() and "clean run" not in done.out + done.err, args


def test_short_chaos_run_equals_the_clean_run():
    """Every kind killed exactly once over a short run (the default suite's version): the last
    kills of a --max-kills budget go to the kinds not killed yet, so 6 kills are one of each, the
    SIGTERM and the SIGKILL of the driver among them. The kills come within the first iterations
    (a kill every 1-2 s, each driver kill followed by a resume), so 10 iterations leave the run room
    to go on after them; the whole state is compared, not only the weights. A narrow network on 16 px images and two of
    the smoke config's groups and no learner started ahead: every process the kills restart builds
    the network, each group has a learner to start, and what is compared does not depend on any of
    these. Two rollout workers, pipelined (the default): the run on Ray, faults and all, must equal
    the serial run, which is also the default suite's check that a Ray run of several workers
    equals the one-process run (``tests/test_pipeline.py`` has the fault-free comparison, slow).
    Both policies' learners share one process, as in the shipped stream and demo configs
    (``runtime.learners_per_process``): the learner killed is that process, and the run must
    still equal the serial run (the fault-free run with one learner process, which also counts the
    processes: ``tests/test_pipeline.py``, slow)."""
    report, _ = _chaos("--interval", "1,2", "--seed", "1", "--max-kills", str(len(KINDS)),
                       *_sets("runtime.total_env_steps=4000", "network.channels=[2,4]", "network.hidden=8",
                              "env.image_size=16", "env.tasks=[reach,push]", "runtime.num_workers=2",
                              "runtime.learner_ahead=false", "runtime.learners_per_process=2"))  # fmt: skip
    assert report["kills"] == {k: 1 for k in KINDS}, report["kills"]
    _assert_passed(report)


@pytest.mark.slow
def test_a_run_without_its_faults_fails_the_verdict():
    """Nothing is killed (the first kill would come after the run's end): the runs are equal, but
    the verdict fails, exit status 1, and says which kind was never killed."""
    report, stderr = _chaos("--kinds", "api", "--interval", "600,600", *_sets("runtime.total_env_steps=800"))
    _assert_equal_to_clean(report)
    assert report["kills"] == {"api": 0} and report["kills_total"] == 0
    assert not report["verdict"] and len(report["failures"]) == 1 and "no api was killed" in report["failures"][0]
    assert "FAIL: no api was killed" in stderr


@pytest.mark.slow
def test_chaos_run_with_twenty_kills_equals_the_clean_run():
    report, _ = _chaos("--seed", "0", "--max-kills", "24", *_sets("runtime.total_env_steps=8000"), timeout=3000)
    _assert_passed(report)
    assert report["kills_total"] >= TARGET_KILLS
    assert all(report["kills"][k] >= 1 for k in KINDS), report["kills"]


@pytest.mark.slow
@pytest.mark.parametrize("lose", ["workers", "learners"])
def test_losing_a_node_mid_run_changes_nothing(lose):
    report, _ = _chaos("--node-loss", lose, *_sets("runtime.total_env_steps=4000"))
    n = report["node_loss"]
    assert n["node_removed"]
    wanted = "worker-" if lose == "workers" else "learner-"
    lost = [name for name in n["on_lost_node"] if name.startswith(wanted)]
    assert lost and set(lost) <= set(n["moved_to_head"])  # they ran on the lost node and came back on the head
    _assert_passed(report)
