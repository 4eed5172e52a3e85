"""What one evaluation pass runs: the (task, g) pairs, their seeds, the policy choices, the rows.

An evaluation pass covers every base task x every element of the run's group. Each pair is
marked ``seen`` (the stream scheduled it before the pass), ``held_out`` (the stream never
schedules it: zero-shot generalization) or ``unseen`` (trainable, not reached yet). Every pair
runs ``episodes`` episodes per selection and mode:

* selection ``agnostic``: the policy the bank picks from each episode's own first frames (a
  what-if: the bank does not change), as a deployed agent would: the bank's rule on that
  episode's frames, and the nearest policy where the rule would start a new one. The pair-level
  choice (the rule on the first frames of all the pair's episodes together, as training assigns
  a batch) is recorded beside it, with the fraction of episodes whose own choice differs;
* selection ``oracle``: the policy that trained on the pair's true group (most assigned training
  episodes of that group), as COVERS-GT would;
* mode ``greedy`` (the policy's mean action) and ``stochastic`` (sampled actions).

Evaluation episodes have their own seeds, a pure function of the run seed, the pair's group, the
pair's element and the episode number, tagged so that they never coincide with a training
episode's seed (``SeedSequence([seed, episode_index])`` in the rollout workers). So every
(group, g, episode) starts from its own initial state: a group's success over its |G| elements
rests on |G| x ``episodes`` distinct states, and the rows count them
(``distinct_initial_states``, from a fingerprint of each episode's initial state mapped back to
the base task, :func:`covers_dist.evaluation.episodes.initial_state_key`). Every pass uses the
same seeds, so successive passes compare like with like. Seeds come in two disjoint splits
(:data:`SPLITS`): the passes during training, which decide a run's stop, use ``stop``;
``covers-dist eval``, the run's report, uses ``report``. Every success figure carries its ``n``
and a Wilson 95% interval (:mod:`covers_dist.evaluation.stats`). Plain Python: no Ray, no torch.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np

from .stats import miss_summary, success_summary

__all__ = [
    "EVAL_SEED_TAG",
    "SPLITS",
    "SELECTIONS",
    "MODES",
    "STATUSES",
    "EvalPair",
    "EvalJob",
    "eval_seed",
    "pair_seeds",
    "eval_pairs",
    "oracle_policies",
    "plan_jobs",
    "pair_rows",
]

#: Tag mixed into every evaluation seed (training seeds are SeedSequence([seed, episode index])).
EVAL_SEED_TAG = 0xE7A1
#: Evaluation splits: ``stop`` for the passes during training (what ``eval.stop_at`` reads),
#: ``report`` for ``covers-dist eval`` (the figures a run reports); their initial states differ.
SPLITS: tuple[str, ...] = ("stop", "report")
#: Mixed into the seeds of the ``stop`` split only (``report`` seeds are those of earlier versions).
STOP_SPLIT_TAG = 0x5709
SELECTIONS: tuple[str, ...] = ("agnostic", "oracle")
MODES: tuple[str, ...] = ("greedy", "stochastic")
STATUSES: tuple[str, ...] = ("seen", "unseen", "held_out")


@dataclass(frozen=True)
class EvalPair:
    """One transformed task of the evaluation grid."""

    task: str
    g: str
    group_id: int
    element_index: int
    status: str

    @property
    def key(self) -> str:
        return f"{self.task}|{self.g}"


@dataclass
class EvalJob:
    """``len(seeds)`` episodes of one pair with one policy in one mode (the unit a worker runs)."""

    pair: EvalPair
    policy_id: int
    mode: str
    seeds: list[int]
    selections: list[str] = field(default_factory=list)
    episodes: list[int] | None = None  # the pair's episode numbers behind ``seeds`` (None: 0, 1, ...)
    episode_selections: list[list[str]] | None = None  # per episode, the selections that chose this policy

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "pair": asdict(self.pair)}


def eval_seed(run_seed: int, group_id: int, element_index: int, episode: int, split: str = "report") -> int:
    """The reset seed of evaluation episode ``episode`` of the pair (group ``group_id``, element
    number ``element_index``) in ``split`` (one of :data:`SPLITS`): a different initial state for
    every (split, group, g, episode), so the passes that decide a run's stop (``stop``) never see
    the initial states of its report (``report``).

    (The test that an equivariant policy scores the same on ``g.T`` as on ``T`` resets both with
    one seed on purpose: tests/test_evaluation.py.)
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}, got {split!r}")
    entropy = [int(run_seed), EVAL_SEED_TAG, int(group_id), int(element_index), int(episode)]
    if split == "stop":
        entropy.insert(2, STOP_SPLIT_TAG)
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def pair_seeds(run_seed: int, pair: "EvalPair", episodes: int, split: str = "report") -> list[int]:
    """The reset seeds of ``pair``'s ``episodes`` evaluation episodes in ``split``."""
    return [eval_seed(run_seed, pair.group_id, pair.element_index, i, split) for i in range(int(episodes))]


def eval_pairs(stream: Any, episodes_done: int, tasks: Sequence[str] | None = None) -> list[EvalPair]:
    """Every (task, g) of ``stream`` (a :class:`~covers_dist.envs.stream.TaskStream`) for ``tasks``
    (default: all of the stream's), marked by what the stream scheduled in its first
    ``episodes_done`` episodes. Unknown task names raise ``ValueError`` naming them."""
    tasks = list(stream.tasks if tasks is None else tasks)
    unknown = [t for t in tasks if t not in stream.tasks]
    if unknown:
        raise ValueError(f"task(s) {unknown} are not in this run; it trained on {list(stream.tasks)}")
    seen = scheduled_pairs(stream, episodes_done)
    held = set(stream.held_out_pairs)
    pairs = []
    for task in tasks:
        for j, g in enumerate(stream.group):
            key = (task, g.name)
            status = "held_out" if key in held else ("seen" if key in seen else "unseen")
            pairs.append(EvalPair(task, g.name, stream.group_id(task), j, status))
    return pairs


def scheduled_pairs(stream: Any, episodes_done: int) -> set[tuple[str, str]]:
    """(task, element name) pairs of the segments the stream started in its first ``episodes_done``."""
    segments = -(-int(episodes_done) // stream.episodes_per_task)  # ceil: a started segment counts
    return {stream.task_at(s * stream.episodes_per_task).key for s in range(segments)}


def oracle_policies(confusion: dict[str, Any]) -> dict[int, int]:
    """{true group id: the policy that served most of its training episodes} from a bank's
    confusion table (``{"policies", "groups", "counts"}``; ties: the lowest policy id)."""
    policies, groups, counts = confusion.get("policies", []), confusion.get("groups", []), confusion.get("counts", [])
    out: dict[int, int] = {}
    if not policies or not groups:
        return out
    table = np.asarray(counts, dtype=np.int64).reshape(len(policies), len(groups))
    for j, gid in enumerate(groups):
        if table[:, j].sum() > 0:
            out[int(gid)] = int(policies[int(np.argmax(table[:, j]))])
    return out


def plan_jobs(
    pairs: Iterable[EvalPair],
    agnostic: dict[str, int | Sequence[int]],
    oracle: dict[int, int],
    run_seed: int,
    episodes: int,
    modes: Sequence[str] = MODES,
    selections: Sequence[str] = SELECTIONS,
    split: str = "report",
) -> list[EvalJob]:
    """One job per (pair, distinct chosen policy, mode), over the episodes that policy acts in.

    ``agnostic[pair key]``: one policy for every episode of the pair, or one per episode (each
    episode's own choice). A policy chosen by both selections for an episode runs it once."""
    jobs = []
    for pair in pairs:
        seeds = pair_seeds(run_seed, pair, episodes, split)
        need: dict[int, dict[int, list[str]]] = {}  # policy -> episode -> selections
        for sel in selections:
            chosen = agnostic.get(pair.key) if sel == "agnostic" else oracle.get(pair.group_id)
            if chosen is None:
                continue
            per_episode = [chosen] * episodes if isinstance(chosen, (int, np.integer)) else list(chosen)
            if len(per_episode) != episodes:
                raise ValueError(f"{pair.key}: {len(per_episode)} chosen policies for {episodes} episodes")
            for i, pid in enumerate(per_episode):
                need.setdefault(int(pid), {}).setdefault(i, []).append(sel)
        for pid, by_episode in sorted(need.items()):
            idx = sorted(by_episode)
            sels = list(dict.fromkeys(s for i in idx for s in by_episode[i]))
            for mode in modes:
                jobs.append(EvalJob(pair, pid, mode, [seeds[i] for i in idx], sels, idx, [by_episode[i] for i in idx]))
    return jobs


def pair_rows(
    pairs: Sequence[EvalPair],
    jobs: Sequence[EvalJob],
    outcomes: Sequence[dict[str, list[float]]],
    choices: dict[str, dict[str, Any]],
    oracle: dict[int, int],
    episode_choices: dict[str, list[int]] | None = None,
) -> list[dict[str, Any]]:
    """Per pair: status, chosen policies and, per ``mode/selection``, success (with ``n``, ``successes``,
    ``ci95`` and ``distinct_initial_states``), mean return and, where the env reports how close an
    episode came, how far the failures stayed (:func:`~covers_dist.evaluation.stats.miss_summary`).

    ``episode_choices[pair key]``: the policy each episode's own first frames chose (the agnostic
    selection's acting policies); the row then gives them and ``episode_choice_disagreement``, the
    fraction of episodes whose own choice differs from the pair-level choice (``choices``)."""
    episode_choices = episode_choices or {}
    # (pair, selection, mode) -> episode number -> (acting policy, its outcome)
    acted: dict[tuple[str, str, str], dict[int, tuple[int, dict[str, Any]]]] = {}
    for job, out in zip(jobs, outcomes):
        numbers = job.episodes if job.episodes is not None else list(range(len(job.seeds)))
        for j, i in enumerate(numbers):
            one = {k: (v[j] if isinstance(v, list) and len(v) == len(numbers) else None) for k, v in out.items()}
            chosen_by = job.episode_selections[j] if job.episode_selections is not None else job.selections
            for sel in chosen_by:
                acted.setdefault((job.pair.key, sel, job.mode), {})[i] = (job.policy_id, one)
    results: dict[str, dict[str, dict[str, Any]]] = {p.key: {} for p in pairs}
    for (key, sel, mode), by_number in acted.items():
        got = [by_number[i] for i in sorted(by_number)]
        out = {k: [e[k] for _, e in got] for k in got[0][1]}
        pids = [pid for pid, _ in got]
        summary = {**success_summary(out["success"], out.get("state_key")), **miss_summary(out["success"], out.get("closest"))}
        results[key][f"{mode}/{sel}"] = {
            "policy_id": max(set(pids), key=lambda q: (pids.count(q), -q)),
            **({"policies": pids} if len(set(pids)) > 1 else {}),
            **summary,
            "return": float(np.mean(out["return"])),
            "episodes": len(got),
        }
    rows = []
    for p in pairs:
        choice = choices.get(p.key, {})
        row = {
            "task": p.task,
            "g": p.g,
            "group_id": p.group_id,
            "status": p.status,
            "agnostic_policy": choice.get("policy_id"),
            "agnostic_decision": choice.get("decision"),
            "agnostic_distance": choice.get("nearest_distance"),
            "oracle_policy": oracle.get(p.group_id),
            "results": results[p.key],
        }
        own = episode_choices.get(p.key)
        if own is not None:
            row["episode_policies"] = list(own)
            pair_level = choice.get("policy_id")
            row["episode_choice_disagreement"] = float(np.mean([q != pair_level for q in own])) if own else None
        rows.append(row)
    return rows
