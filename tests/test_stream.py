"""The task stream: seeded, indexable, held-out pairs never scheduled, groups recur in random order."""

import json
from collections import Counter

import pytest

from covers_dist.config import EnvConfig
from covers_dist.envs.stream import StreamTask, TaskStream
from covers_dist.symmetry import get_group

TOY = ["reach", "push", "avoid"]
MW = ["reach-v3", "button-press-topdown-v3", "drawer-close-v3", "plate-slide-v3"]


def _schedule(stream, segments):
    return [t.key for t in stream.segments(segments)]


def test_same_seed_same_schedule_other_seed_other_schedule():
    a = TaskStream(MW, "D4", episodes_per_task=5, held_out=4, seed=3)
    b = TaskStream(MW, "D4", episodes_per_task=5, held_out=4, seed=3)
    c = TaskStream(MW, "D4", episodes_per_task=5, held_out=4, seed=4)
    assert _schedule(a, 40) == _schedule(b, 40)
    assert a.held_out_pairs == b.held_out_pairs
    assert _schedule(a, 40) != _schedule(c, 40)


def test_a_new_task_every_n_episodes():
    stream = TaskStream(TOY, "D4", episodes_per_task=7, seed=1)
    tasks = [stream.next_task() for _ in range(70)]
    for i, t in enumerate(tasks):
        assert isinstance(t, StreamTask) and t.episode == i and t.segment == i // 7
        assert t.key == tasks[(i // 7) * 7].key
    keys = [tasks[s * 7].key for s in range(10)]
    assert all(keys[s] != keys[s + 1] for s in range(9))


def test_groups_arrive_in_random_order_and_recur():
    stream = TaskStream(MW, "D4", episodes_per_task=1, seed=0)
    rounds = [[t.task for t in stream.segments(4, start=4 * r)] for r in range(12)]
    for order in rounds:
        assert sorted(order) == sorted(MW)  # every group once per round
    assert len({tuple(o) for o in rounds}) > 3  # in changing orders
    assert all(rounds[r][-1] != rounds[r + 1][0] for r in range(11))  # never twice in a row
    assert len({r[0] for r in rounds}) > 1  # no fixed first group


def test_held_out_pairs_are_never_scheduled_and_the_rest_recur():
    stream = TaskStream(MW, "D4", episodes_per_task=1, held_out=6, seed=2)
    held = set(stream.held_out_pairs)
    assert len(held) == 6
    seen = Counter(t.key for t in stream.segments(4 * 8 * 3))
    assert not held & set(seen)
    assert set(seen) == set(stream.training_pairs)  # every trained pair appears ...
    assert min(seen.values()) >= 2  # ... and recurs
    assert len(stream.training_pairs) + len(held) == 4 * 8


def test_every_task_keeps_a_trained_pair_even_when_holding_out_the_most():
    stream = TaskStream(TOY, "C4", held_out=9, seed=5)
    assert len(stream.held_out_pairs) == 9
    assert Counter(t for t, _ in stream.training_pairs) == {t: 1 for t in TOY}
    with pytest.raises(ValueError, match="held_out=10 is too many"):
        TaskStream(TOY, "C4", held_out=10)


def test_subgroups_use_only_their_elements():
    names = {g.name for g in get_group("D2")}
    stream = TaskStream(TOY, "D2", episodes_per_task=1, seed=0)
    assert {t.g.name for t in stream.segments(24)} == names
    trivial = TaskStream(["only"], "trivial", episodes_per_task=3, seed=0)
    assert {t.key for t in trivial.segments(5)} == {("only", "e")}


def test_indexing_equals_sequential_use_and_resume():
    stream = TaskStream(MW, "C4", episodes_per_task=3, held_out=2, seed=9)
    sequential = [stream.next_task() for _ in range(50)]
    fresh = TaskStream(MW, "C4", episodes_per_task=3, held_out=2, seed=9)
    assert [fresh.task_at(i) for i in range(50)] == sequential
    state = json.loads(json.dumps(stream.state_dict()))  # JSON-safe checkpoint
    assert state["episode"] == 50
    resumed = TaskStream(MW, "C4", episodes_per_task=3, held_out=2, seed=9)
    resumed.load_state_dict(state)
    assert [resumed.next_task() for _ in range(10)] == [stream.next_task() for _ in range(10)]


def test_load_state_rejects_another_stream():
    stream = TaskStream(TOY, "D4", seed=1)
    other = TaskStream(TOY, "D4", seed=2)
    with pytest.raises(ValueError, match="seed=2 but this stream has seed=1"):
        stream.load_state_dict(other.state_dict())
    with pytest.raises(ValueError, match="lacks"):
        stream.load_state_dict({"episode": 3})
    state = stream.state_dict()
    state["episode"] = -1
    with pytest.raises(ValueError, match="episode index"):
        stream.load_state_dict(state)


def test_group_ids_and_config():
    cfg = EnvConfig(suite="metaworld", tasks=MW, group="D4", image_size=64, episodes_per_task=4, held_out=3)
    stream = TaskStream.from_config(cfg, seed=0)
    assert [stream.group_id(t) for t in MW] == [0, 1, 2, 3]
    assert all(t.group_id == MW.index(t.task) for t in stream.segments(8))
    assert stream.episodes_per_task == 4 and len(stream.held_out_pairs) == 3
    with pytest.raises(ValueError, match="unknown task 'push'"):
        stream.group_id("push")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(tasks=[]), "non-empty list"),
        (dict(tasks="reach"), "non-empty list"),
        (dict(tasks=["a", "a"]), "duplicates"),
        (dict(tasks=["a", 3]), "non-empty strings"),
        (dict(tasks=["a"], group="D5"), "unknown symmetry group"),
        (dict(tasks=["a"], episodes_per_task=0), "episodes_per_task"),
        (dict(tasks=["a"], held_out=-1), "held_out"),
        (dict(tasks=["a"], seed=1.5), "seed"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        TaskStream(**kwargs)
    stream = TaskStream(["a"])
    with pytest.raises(ValueError, match="episode index"):
        stream.task_at(-3)
