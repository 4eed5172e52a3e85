"""What the driver counts of the episodes it records, and the metrics row of an iteration.

:class:`EpisodeTally` keeps, per task group, when the group first appeared and the env steps
spent on it (evaluation metrics need both), the latest batch's training success and return, and
how many episodes were acted by a policy other than the one they were then assigned to, and each
policy's latest training successes (what fades its exploration noise, ``ppo.noise_fade_success``).
:func:`iteration_row` turns an iteration into the row written to metrics.jsonl (names in
:class:`~covers_dist.runtime.metrics.M`).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..ppo.noise import FADE_WINDOW
from .metrics import M

__all__ = ["EpisodeTally", "iteration_row", "loss_fields"]


class EpisodeTally:
    """Per-group counts over the recorded episodes (the driver's bookkeeping, saved in checkpoints)."""

    def __init__(self, tasks: list[str]) -> None:
        self.groups: dict[str, dict[str, Any]] = {t: {"first_episode": None, "env_steps": 0} for t in tasks}
        self.success: dict[str, float] = {}  # the latest batch of each task group seen so far
        self.returns: dict[str, float] = {}
        self.acted_other = 0  # episodes acted by a policy other than the one they were assigned to
        self.last: list[dict[str, Any]] = []  # the last batch's episode summaries
        self.policy_success: dict[int, list[float]] = {}  # per acting policy, its last FADE_WINDOW successes

    def record(self, summaries: list[dict[str, Any]], assigned: int) -> None:
        """Count a batch of episode summaries, all assigned to policy ``assigned``."""
        batch_success: dict[str, list[float]] = {}
        batch_return: dict[str, list[float]] = {}
        for s in summaries:
            s["assigned_policy"] = assigned
            self.acted_other += int(s["policy_id"] != assigned)
            info = self.groups.setdefault(s["task"], {"first_episode": None, "env_steps": 0})
            if info["first_episode"] is None:
                info["first_episode"] = int(s["episode_index"])
            info["env_steps"] += int(s["length"])
            batch_success.setdefault(s["task"], []).append(s["success"])
            batch_return.setdefault(s["task"], []).append(s["return"])
            recent = self.policy_success.setdefault(int(s["policy_id"]), [])
            recent.append(float(s["success"]))
            del recent[:-FADE_WINDOW]
        for task in batch_success:
            self.success[task] = float(np.mean(batch_success[task]))
            self.returns[task] = float(np.mean(batch_return[task]))
        self.last = summaries

    def episode_rows(self, env_steps: int, iteration: int) -> list[dict[str, Any]]:
        """The last batch's episodes as rows of episodes.jsonl (env steps counted up to each one)."""
        steps = env_steps - sum(s["length"] for s in self.last)
        rows = []
        for s in self.last:
            steps += s["length"]
            rows.append({**s, M.ENV_STEPS: steps, M.ITERATION: iteration})
        return rows


def loss_fields(stats: dict[str, Any]) -> dict[str, Any]:
    """A learner's update statistics as ``ppo/<stat>`` metrics (numbers only)."""
    return {
        f"{M.LOSS}/{key}": value
        for key, value in stats.items()
        if isinstance(value, (int, float)) and not isinstance(value, bool)
    }


def iteration_row(
    trainer: Any, record: dict[str, Any], stats: dict[str, Any], clustering_metrics: dict[str, Any]
) -> dict[str, Any]:
    """The metrics row of the iteration ``trainer`` (a :class:`~covers_dist.runtime.driver.Trainer`)
    just stepped: counters, the assignment ``record``, the clustering's metrics, training success
    and return per group, phase times and the update's statistics."""
    tally: EpisodeTally = trainer.tally
    dists = [d for d in record.get("distances", {}).values() if d is not None]
    elapsed = max(time.monotonic() - trainer.clock_start, 1e-9)
    row: dict[str, Any] = {
        M.ITERATION: trainer.iteration,
        M.EPISODES: trainer.next_episode,
        M.ENV_STEPS: trainer.env_steps,
        M.POLICY: trainer.current_policy,
        M.NUM_POLICIES: clustering_metrics.get("num_policies", len(trainer.weights.versions)),
        M.ARI: clustering_metrics.get("ari", float("nan")),
        M.NEW_POLICY: bool(record.get("new", False)),
        M.WRONG_POLICY: tally.acted_other / max(trainer.next_episode, 1),
        M.DISTANCE_MIN: min(dists) if dists else float("nan"),
        M.STEPS_PER_S: (trainer.env_steps - trainer.clock_steps) / elapsed,
        "wall_time": time.time(),
    }
    for task in tally.success:
        row[f"{M.SUCCESS}/{task}"] = tally.success[task]
        row[f"{M.RETURN}/{task}"] = tally.returns[task]
    if trainer.cfg.ppo.noise_beta > 0.0:
        row[M.NOISE_BETA] = trainer.noise_beta
    for name, secs in trainer.phase_time.items():
        row[f"{M.TIME}/{name}"] = secs
    row.update(loss_fields(stats))
    return row
