"""The task stream: which transformed task ``(task, g)`` the agent is in at every episode.

Suite-agnostic (toy or Meta-World task names alike). The stream is cut into segments of
``episodes_per_task`` episodes; each segment is one ``(task, g)``. Segments come in rounds: in
every round each task group appears once, in a random order (a round never starts with the
group that ended the previous one), so groups arrive in random order and recur. The k-th time
a group appears it uses the next element of a seeded shuffle of the group elements not held
out, so every trainable ``(task, g)`` pair recurs too. ``held_out``
pairs (seeded) are never scheduled: they are kept for generalization tests, and every task keeps
at least one trained pair.

Everything is a pure function of the seed and the episode index, so parallel workers and a
resumed run agree without talking: ``stream.task_at(i)``. The stream knows the true group and
element of every episode (for metrics); nothing the agent sees carries them. The position
``stream.episode`` (advanced by :meth:`TaskStream.next_task`) is all the state a checkpoint
needs: :meth:`TaskStream.state_dict` is JSON-safe.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from ..symmetry import GroupElement, get_group

__all__ = ["TaskStream", "StreamTask"]

_ROUND, _ELEMENTS, _HELD_OUT = 1, 2, 3  # seed-sequence tags for independent random streams


@dataclass(frozen=True)
class StreamTask:
    """The transformed task of one episode. ``g`` and ``group_id`` are for metrics only."""

    task: str
    g: GroupElement
    group_id: int
    segment: int
    episode: int

    @property
    def key(self) -> tuple[str, str]:
        """``(task, element name)``: the identity of the transformed task."""
        return (self.task, self.g.name)


class TaskStream:
    """A reproducible schedule of transformed tasks (see the module docstring)."""

    def __init__(
        self,
        tasks: list[str] | tuple[str, ...],
        group: str = "D4",
        episodes_per_task: int = 20,
        held_out: int = 0,
        seed: int = 0,
    ) -> None:
        if isinstance(tasks, str) or not isinstance(tasks, (list, tuple)) or not tasks:
            raise ValueError(f"tasks must be a non-empty list of task names, got {tasks!r}")
        if not all(isinstance(t, str) and t for t in tasks):
            raise TypeError(f"tasks must be non-empty strings, got {list(tasks)!r}")
        if len(set(tasks)) != len(tasks):
            raise ValueError(f"tasks has duplicates: {list(tasks)}")
        checks = (("episodes_per_task", episodes_per_task, 1), ("held_out", held_out, 0), ("seed", seed, 0))
        for name, value, low in checks:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        self.tasks = tuple(tasks)
        self.group = get_group(group)
        self.episodes_per_task = int(episodes_per_task)
        self.held_out = int(held_out)
        self.seed = int(seed)
        limit = len(self.tasks) * (len(self.group) - 1)
        if self.held_out > limit:
            raise ValueError(
                f"held_out={held_out} is too many: at most {limit} of the {len(self.tasks) * len(self.group)} "
                f"(task, g) pairs can be held out so that every task keeps one trained pair"
            )
        self._held = self._choose_held_out()
        self._trainable = {
            t: tuple(g for g in self.group if (t, g.name) not in self._held) for t in self.tasks
        }
        self.episode = 0

    # ---- schedule --------------------------------------------------------------------------------
    def _rng(self, *tags: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, *tags]))

    def _choose_held_out(self) -> frozenset[tuple[str, str]]:
        pairs = [(t, g.name) for t in self.tasks for g in self.group]
        order = self._rng(_HELD_OUT).permutation(len(pairs))
        left = {t: len(self.group) for t in self.tasks}
        held: set[tuple[str, str]] = set()
        for i in order:
            if len(held) == self.held_out:
                break
            task, name = pairs[i]
            if left[task] > 1:
                held.add((task, name))
                left[task] -= 1
        return frozenset(held)

    def _round_order(self, rnd: int) -> np.ndarray:
        """Task order of round ``rnd``: a seeded permutation that never repeats the previous
        round's last task first (with two tasks the groups simply alternate)."""
        n = len(self.tasks)
        if n == 2 and rnd > 0:
            return self._round_order(0)
        order = self._rng(_ROUND, rnd).permutation(n)
        if n > 2 and rnd > 0:
            # swapping the first two never changes a round's last task, so this needs no recursion
            if order[0] == self._rng(_ROUND, rnd - 1).permutation(n)[-1]:
                order[0], order[1] = order[1], order[0]
        return order

    def _element(self, task_index: int, occurrence: int) -> GroupElement:
        task = self.tasks[task_index]
        elements = self._trainable[task]
        cycle, pos = divmod(occurrence, len(elements))
        order = self._rng(_ELEMENTS, task_index, cycle).permutation(len(elements))
        return elements[int(order[pos])]

    def segment_of(self, episode: int) -> int:
        """Index of the segment (``episodes_per_task`` episodes) holding ``episode``."""
        return self._check_index(episode) // self.episodes_per_task

    def task_at(self, episode: int) -> StreamTask:
        """The transformed task of episode ``episode`` (any index: no state is read or changed)."""
        segment = self.segment_of(episode)
        rnd, pos = divmod(segment, len(self.tasks))
        task_index = int(self._round_order(rnd)[pos])
        # each round holds every task once, so this is the task's (rnd)-th appearance
        g = self._element(task_index, rnd)
        return StreamTask(self.tasks[task_index], g, task_index, segment, int(episode))

    def next_task(self) -> StreamTask:
        """The task of the current position, then advance by one episode."""
        out = self.task_at(self.episode)
        self.episode += 1
        return out

    def segments(self, count: int, start: int = 0) -> list[StreamTask]:
        """The first episode's task of ``count`` segments from segment ``start`` on."""
        return [self.task_at((start + s) * self.episodes_per_task) for s in range(count)]

    def __iter__(self) -> Iterator[StreamTask]:
        while True:
            yield self.next_task()

    # ---- facts for metrics and evaluation ----------------------------------------------------
    def group_id(self, task: str) -> int:
        """Index of a base task (the true group label of its transformed copies)."""
        try:
            return self.tasks.index(task)
        except ValueError:
            raise ValueError(f"unknown task {task!r}; the stream has {list(self.tasks)}") from None

    @property
    def held_out_pairs(self) -> list[tuple[str, str]]:
        """(task, element name) pairs never scheduled, sorted."""
        return sorted(self._held)

    @property
    def training_pairs(self) -> list[tuple[str, str]]:
        """(task, element name) pairs the stream schedules."""
        return [(t, g.name) for t in self.tasks for g in self._trainable[t]]

    # ---- checkpointing -----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """JSON-safe: the stream's definition and its position."""
        return {
            "tasks": list(self.tasks),
            "group": self.group.name,
            "episodes_per_task": self.episodes_per_task,
            "held_out": self.held_out,
            "seed": self.seed,
            "episode": self.episode,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resume at ``state["episode"]``; the definition must match this stream's."""
        if not isinstance(state, dict):
            raise TypeError(f"stream state must be a dict, got {type(state).__name__}")
        mine = self.state_dict()
        missing = sorted(set(mine) - set(state))
        if missing:
            raise ValueError(f"stream state lacks {missing}")
        for key in ("tasks", "group", "episodes_per_task", "held_out", "seed"):
            theirs = list(state[key]) if key == "tasks" and isinstance(state[key], (list, tuple)) else state[key]
            if theirs != mine[key]:
                raise ValueError(f"stream state has {key}={state[key]!r} but this stream has {key}={mine[key]!r}")
        self.episode = self._check_index(state["episode"])

    @classmethod
    def from_config(cls, env_cfg: Any, seed: int) -> "TaskStream":
        """The stream an :class:`~covers_dist.config.EnvConfig` describes."""
        return cls(list(env_cfg.tasks), env_cfg.group, env_cfg.episodes_per_task, env_cfg.held_out, seed)

    @staticmethod
    def _check_index(episode: Any) -> int:
        if isinstance(episode, bool) or not isinstance(episode, (int, np.integer)) or episode < 0:
            raise ValueError(f"episode index must be an integer >= 0, got {episode!r}")
        return int(episode)

    def __repr__(self) -> str:
        return (
            f"TaskStream(tasks={list(self.tasks)}, group={self.group.name!r}, episodes_per_task="
            f"{self.episodes_per_task}, held_out={self.held_out}, seed={self.seed}, episode={self.episode})"
        )
