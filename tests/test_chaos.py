"""Faults change nothing: a run whose workers, learners, clustering actor, HTTP service and driver
are killed at random ends where the clean run ends; so does a run that loses a node."""

import json
import subprocess
import sys

import pytest

from covers_dist.bench.chaos import KINDS, TARGET_KILLS, compare

# a short stream: 400 env steps per iteration, learners on both sides of a kill
SHORT = ["runtime.checkpoint_every=2", "ppo.epochs=2"]


def _chaos(*args, timeout=1500):
    """``covers-dist bench chaos --json`` in its own process (it starts its own Ray instances)."""
    cmd = [sys.executable, "-m", "covers_dist", "bench", "chaos", "--json", *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    lines = done.stdout.strip().splitlines()
    # exit 1 with a report: the runs differ (the asserts below say how); without one: the bench failed
    assert done.returncode in (0, 1) and lines, f"exit {done.returncode}; stderr:\n{done.stderr[-4000:]}"
    return json.loads(lines[-1]), done.stderr


def _sets(*overrides):
    return [x for o in (*SHORT, *overrides) for x in ("--set", o)]


def _assert_equal_to_clean(report):
    c = report["comparison"]
    assert c["assignments_identical"], c
    assert c["assigned_exactly_once"] and c["logged_exactly_once"], c
    assert c["logged_doubles"] == 0 and c["logged_missing"] == 0
    assert c["weights_identical"] and c["weights_max_abs_diff"] == 0.0, c
    assert report["equal_to_clean"]


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


def test_bad_chaos_arguments_are_refused_with_a_message():
    for args, words in ((["--interval", "5,1"], "MIN <= MAX"), (["--interval", "x"], "MIN,MAX"),
                        (["--kinds", "worker,gpu"], "--kinds")):  # fmt: skip
        done = subprocess.run([sys.executable, "-m", "covers_dist", "bench", "chaos", *args], capture_output=True, text=True)
        assert done.returncode != 0 and words in done.stderr


def test_short_chaos_run_equals_the_clean_run():
    """Every kind killed at least once over a short run (the default suite's version)."""
    report, _ = _chaos("--interval", "1.5,3", "--seed", "1", "--max-kills", "8", *_sets("runtime.total_env_steps=4000"))
    _assert_equal_to_clean(report)
    assert report["kills_total"] >= 3


@pytest.mark.slow
def test_chaos_run_with_twenty_kills_equals_the_clean_run():
    report, _ = _chaos("--seed", "0", "--max-kills", "24", *_sets("runtime.total_env_steps=8000"), timeout=3000)
    _assert_equal_to_clean(report)
    assert report["kills_total"] >= TARGET_KILLS
    assert set(report["kills"]) == set(KINDS)


@pytest.mark.slow
@pytest.mark.parametrize("lose", ["workers", "learners"])
def test_losing_a_node_mid_run_changes_nothing(lose):
    report, _ = _chaos("--node-loss", lose, *_sets("runtime.total_env_steps=4000"))
    n = report["node_loss"]
    assert n["node_removed"]
    wanted = "worker-" if lose == "workers" else "learner-"
    lost = [name for name in n["on_lost_node"] if name.startswith(wanted)]
    assert lost and set(lost) <= set(n["moved_to_head"])  # they ran on the lost node and came back on the head
    _assert_equal_to_clean(report)
