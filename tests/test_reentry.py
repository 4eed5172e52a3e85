"""Re-entry changes (covers_dist.evaluation.reentry) against hand-computed answers, and their table."""

import math

import pytest

from covers_dist.evaluation.compare import reentry_table
from covers_dist.evaluation.reentry import reentry_changes, segments


def ep(i, task, ret, success=0.0):
    return {"episode_index": i, "task": task, "return": ret, "success": success}


def stream(*blocks):
    """Episodes from (task, [returns], [successes]) blocks, indexed in order."""
    out, i = [], 0
    for task, rets, succ in blocks:
        for r, s in zip(rets, succ):
            out.append(ep(i, task, r, s))
            i += 1
    return out


def test_segments_are_maximal_runs_in_index_order_and_a_repeated_index_keeps_its_last_row():
    eps = stream(("a", [1, 2], [0, 0]), ("b", [3], [0]), ("a", [4], [1]))
    resumed = [*reversed(eps), ep(3, "a", 40.0, 1.0)]  # out of order, index 3 written again after a resume
    segs = segments(resumed)
    assert [(t, [e["return"] for e in es]) for t, es in segs] == [("a", [1, 2]), ("b", [3]), ("a", [40.0])]
    with pytest.raises(ValueError, match="lacks episode_index or task"):
        segments([{"task": "a", "return": 1.0}])


def test_changes_across_gaps_by_hand():
    eps = stream(
        ("a", [0, 10, 20], [0, 0, 1]),  # last 2: 10, 20 -> mean 15; success 0.5
        ("b", [5, 5], [0, 0]),
        ("a", [7], [1]),  # shorter than the window: not a re-entry, and not the "before" of the next
        ("a2", [1, 1], [0, 0]),  # another task in between
        ("a", [11, 13, 100], [1, 0, 1]),  # first 2: 11, 13 -> 12 (change -3); success 0.5 -> 0.5
        ("b", [9, 1], [1, 1]),  # b: 5 -> 5 (change 0); success 0 -> 1
        ("a", [18, 20], [1, 1]),  # before: last 2 of the previous a (13, 100) -> 56.5; after 19 (-37.5)
    )
    got = reentry_changes(eps, window=2)
    assert set(got) == {"a", "b"}  # a2 never came back
    a = got["a"]
    assert a["reentries"] == 2
    assert a["return_before"] == pytest.approx((15 + 56.5) / 2) and a["return_after"] == pytest.approx((12 + 19) / 2)
    assert a["return_change"]["mean"] == pytest.approx((-3 - 37.5) / 2)
    assert a["return_change"]["se"] == pytest.approx(abs(-3 + 37.5) / 2)  # two values: std(ddof 1) / sqrt(2)
    assert a["success_before"] == pytest.approx((0.5 + 0.5) / 2) and a["success_after"] == pytest.approx((0.5 + 1) / 2)
    b = got["b"]
    assert b["reentries"] == 1 and b["return_change"]["mean"] == 0.0 and math.isnan(b["return_change"]["se"])
    assert b["success_change"]["mean"] == 1.0
    # a window of 1: the one-episode segment of a now counts
    assert reentry_changes(eps, window=1)["a"]["reentries"] == 3
    assert reentry_changes(stream(("a", [1], [0]), ("b", [2], [0])), window=1) == {}
    with pytest.raises(ValueError, match="window must be >= 1"):
        reentry_changes(eps, window=0)


def test_the_table_names_each_group_and_says_n_a_where_a_run_has_none():
    eps = stream(("reach-v3", [10, 20], [0, 1]), ("drawer-close-v3", [1, 1], [0, 0]), ("reach-v3", [30, 40], [1, 1]))
    data = {
        "tasks": ["reach-v3", "drawer-close-v3"],
        "runs": [
            {"label": "covers", "seed": 0, "reentry": reentry_changes(eps, window=2)},
            {"label": "equi", "seed": 0, "reentry": None},
        ],
    }
    md = reentry_table(data)
    assert "| method | seed | Goal Reach | Drawer Close |" in md
    assert "| covers | 0 | 15 -> 35 (+20 +- nan); success 0.50 -> 1.00; n=1 | n/a |" in md
    assert "| equi | 0 | n/a | n/a |" in md
    assert reentry_table({"tasks": data["tasks"], "runs": [data["runs"][1]]}) is None


def test_value_fit_attributes_each_update_to_its_batch_group_by_hand():
    from covers_dist.evaluation.reentry import value_fit

    # iterations 1-4: batches of a, a, b, a+b (mixed: left out)
    episodes = [
        {"iteration": 1, "task": "a"},
        {"iteration": 2, "task": "a"},
        {"iteration": 3, "task": "b"},
        {"iteration": 4, "task": "a"},
        {"iteration": 4, "task": "b"},
    ]
    metrics = [
        {"iteration": 1, "ppo/explained_variance": 0.1},
        {"iteration": 2, "ppo/explained_variance": 0.2},
        {"iteration": 3, "ppo/explained_variance": 0.3},
        {"iteration": 4, "ppo/explained_variance": 0.4},
        {"iteration": 4, "ppo/explained_variance": 0.5},  # written again after a resume: this one counts
        {"iteration": 5, "ppo/explained_variance": float("nan")},  # no statistics worth counting
    ]
    # sequential: each row reports its own batch
    assert value_fit(metrics, episodes, lag=0) == {
        "a": {"updates": 2, "explained_variance": pytest.approx(0.15)},
        "b": {"updates": 1, "explained_variance": pytest.approx(0.3)},
    }
    # pipelined: each row reports the previous iteration's batch (row 2 -> a, 3 -> a, 4 -> b, 5 -> mixed)
    assert value_fit(metrics, episodes, lag=1) == {
        "a": {"updates": 2, "explained_variance": pytest.approx(0.25)},
        "b": {"updates": 1, "explained_variance": pytest.approx(0.5)},
    }
    # rows that name their batch are read by that name, whatever the lag
    named = [{**m, "ppo/batch_iteration": b} for m, b in zip(metrics, (1, 1, 3, 2, 3, 4))]
    assert value_fit(named, episodes, lag=1) == value_fit(named, episodes, lag=0) == {
        "a": {"updates": 2, "explained_variance": pytest.approx(0.15)},
        "b": {"updates": 2, "explained_variance": pytest.approx(0.4)},
    }
    with pytest.raises(ValueError, match="lag must be 0"):
        value_fit(metrics, episodes, lag=2)
