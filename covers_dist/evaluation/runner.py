"""One evaluation pass, run on any set of executors, and the ``eval.jsonl`` log.

A pass has three phases:

1. ``frames``: the executors reset every pair's evaluation episodes and return their first
   observations (no policy is involved);
2. ``choose``: the bank's assignment rule picks a policy per pair from those frames (``choose``
   is a what-if: the bank does not change); the oracle policy per group comes from the caller;
3. ``episodes``: the executors run the episodes of every (pair, policy, mode) job and return
   success and return per episode (no frames leave them).

Executors are anything with ``map(method, per_executor_args)`` that calls
``RolloutWorker.<method>`` on each executor (:class:`LocalExecutors` in this process; the
runtime's Ray version on actors). Plain Python: no Ray here.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .protocol import MODES, SELECTIONS, EvalPair, pair_rows, pair_seeds, plan_jobs

__all__ = ["LocalExecutors", "run_evaluation", "EVAL_LOG", "append_pass", "read_passes", "split_evenly"]

EVAL_LOG = "eval.jsonl"


class LocalExecutors:
    """Executors in this process (plain :class:`~covers_dist.runtime.rollout.RolloutWorker` objects)."""

    def __init__(self, workers: Sequence[Any]) -> None:
        if not workers:
            raise ValueError("need at least one evaluation worker")
        self.workers = list(workers)

    @property
    def size(self) -> int:
        return len(self.workers)

    def map(self, method: str, args: Sequence[tuple]) -> list[Any]:
        return [getattr(w, method)(*a) for w, a in zip(self.workers, args)]

    def close(self) -> None:
        for w in self.workers:
            w.close()


def split_evenly(items: Sequence[Any], n: int) -> list[list[Any]]:
    """``items`` dealt round-robin into ``n`` lists (some may be empty)."""
    return [list(items[i::n]) for i in range(n)]


def _gather(executors: Any, method: str, items: Sequence[Any], *extra: Any) -> list[Any]:
    """Run ``method`` over ``items`` spread across the executors; results in ``items`` order."""
    n = executors.size
    parts = split_evenly(list(range(len(items))), n)
    busy = [(i, p) for i, p in enumerate(parts) if p]
    args = [([items[j] for j in p], *extra) for _, p in busy]
    if len(busy) < n:  # map() pairs executors with argument tuples in order: pad idle ones out
        results = executors.map(method, args + [([], *extra)] * (n - len(busy)))[: len(busy)]
    else:
        results = executors.map(method, args)
    out: list[Any] = [None] * len(items)
    for (_, p), res in zip(busy, results):
        for j, r in zip(p, res):
            out[j] = r
    return out


def run_evaluation(
    executors: Any,
    pairs: Sequence[EvalPair],
    choose: Callable[[dict[str, np.ndarray], list[int]], dict[str, Any]],
    oracle: dict[int, int],
    weights_map: dict[int, tuple[int, Any]],
    run_seed: int,
    episodes: int,
    modes: Sequence[str] = MODES,
    selections: Sequence[str] = SELECTIONS,
    log: Callable[[str], None] | None = None,
    new_policy: Callable[[int], tuple[int, Any]] | None = None,
    split: str = "report",
    frames_per_episode: int = 1,
) -> dict[str, Any]:
    """One pass over ``pairs``: returns ``{"pairs": rows, "time_s": {...}, ...}`` (see module doc).

    ``choose(obs, group_ids)`` returns an assignment record (``policy_id``, ``decision``,
    ``nearest_distance``); ``weights_map`` is ``{policy id: (version, weights or handle)}``.
    When the rule would create a policy (decision ``new``), the agent would act with a fresh one:
    ``new_policy(policy_id)`` gives its ``(version, weights)`` (without it such pairs get no
    ``agnostic`` result). The ``agnostic`` episodes are acted by each episode's own choice
    (``choose`` on its ``frames_per_episode`` first frames; the nearest policy of the record's
    ``distances`` where that choice is ``new``); the pair-level choice is recorded beside it.
    ``split``: the seeds' split (:data:`~covers_dist.evaluation.protocol.SPLITS`).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not pairs:
        raise ValueError("no (task, g) pairs to evaluate")
    t0 = time.perf_counter()
    times: dict[str, float] = {}
    if frames_per_episode < 1:
        raise ValueError(f"frames_per_episode must be >= 1, got {frames_per_episode}")
    seeds = {p.key: pair_seeds(run_seed, p, episodes, split) for p in pairs}
    frames = _gather(executors, "eval_first_frames", [(p, seeds[p.key]) for p in pairs])
    times["frames"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    choices: dict[str, dict[str, Any]] = {}
    episode_choices: dict[str, list[int]] = {}
    if "agnostic" in selections:
        k = frames_per_episode
        for p, obs in zip(pairs, frames):
            choices[p.key] = choose(obs, [p.group_id] * len(obs["image"]))
            own = []
            for i in range(len(obs["image"]) // k):
                part = {key: v[i * k : (i + 1) * k] for key, v in obs.items()}
                own.append(episode_policy(choose(part, [p.group_id] * k)))
            episode_choices[p.key] = own
    weights_map = dict(weights_map)
    pair_level = {p: int(c["policy_id"]) for p, c in choices.items()}
    for pid in sorted(set(pair_level.values()) - set(weights_map)):  # "new": a fresh policy would act
        if new_policy is not None:
            weights_map[pid] = new_policy(pid)
    episode_choices = {key: own for key, own in episode_choices.items() if all(q in weights_map for q in own)}
    oracle = {g: p for g, p in oracle.items() if p in weights_map}
    times["choose"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    jobs = plan_jobs(
        pairs, episode_choices, oracle if "oracle" in selections else {}, run_seed, episodes, modes, selections, split
    )
    if log is not None:
        log(
            f"evaluation: {len(pairs)} (task, g) pairs, {len(jobs)} jobs of {episodes} episodes "
            f"on {executors.size} worker(s); frames + choice took {times['frames'] + times['choose']:.1f} s"
        )
    outcomes = _gather(executors, "eval_jobs", jobs, weights_map) if jobs else []
    times["episodes"] = time.perf_counter() - t2
    times["total"] = time.perf_counter() - t0
    own = [q != pair_level.get(key) for key, choices_ in episode_choices.items() for q in choices_]
    return {
        "split": split,
        "seeds": {key: list(v) for key, v in seeds.items()},
        "episode_choice_disagreement": float(np.mean(own)) if own else None,
        "episodes_per_job": int(episodes),
        "modes": list(modes),
        "selections": list(selections),
        "pairs": pair_rows(pairs, jobs, outcomes, choices, oracle, episode_choices),
        "time_s": times,
        "eval_episodes": int(sum(len(o["success"]) for o in outcomes)),
        # different reset states behind the pass (the same state met by two modes or policies counts once)
        "distinct_initial_states": len({k for o in outcomes for k in o.get("state_key", []) if k is not None}),
    }


def episode_policy(record: dict[str, Any]) -> int:
    """The policy that acts in an episode, from the assignment record of its own first frames: the
    record's choice, or where the rule would start a new policy, the nearest one (a deployed agent
    acts with a policy it has)."""
    if record.get("decision") == "new" and record.get("distances"):
        d = {int(k): (float("inf") if v is None else float(v)) for k, v in record["distances"].items()}
        return min(sorted(d), key=lambda q: d[q])
    return int(record["policy_id"])


def append_pass(run_dir: str | Path, ev: dict[str, Any]) -> Path:
    """Append one pass to ``RUN_DIR/eval.jsonl`` (never touches checkpoints)."""
    path = Path(run_dir) / EVAL_LOG
    with open(path, "a") as fh:
        fh.write(json.dumps(ev, default=float) + "\n")
    return path


def read_passes(run_dir: str | Path, missing_ok: bool = True) -> list[dict[str, Any]]:
    """The passes of ``RUN_DIR/eval.jsonl`` by iteration (the newest pass of each iteration); a line
    that does not parse raises ``ValueError`` naming it (a partly written last line is skipped)."""
    path = Path(run_dir) / EVAL_LOG
    if not path.is_file():
        if missing_ok:
            return []
        raise FileNotFoundError(f"{path} does not exist: run `covers-dist eval {run_dir}` first")
    lines = path.read_text().splitlines()
    passes = []
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            ev = json.loads(line)
        except json.JSONDecodeError as e:
            if n == len(lines):  # an interrupted append
                break
            raise ValueError(f"{path}:{n} is not valid JSON ({e})") from None
        if not isinstance(ev, dict) or "pairs" not in ev:
            raise ValueError(f"{path}:{n} is not an evaluation pass (no 'pairs')")
        passes.append(ev)
    # a resumed run repeats the iterations after its checkpoint, and `covers-dist eval` may evaluate
    # an iteration again: the newest pass of each iteration stands, in iteration order
    by_iteration = {ev.get("iteration", -1): ev for ev in passes}
    return [by_iteration[i] for i in sorted(by_iteration)]
