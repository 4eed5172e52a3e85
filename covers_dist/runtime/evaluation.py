"""Evaluation passes for a training run and for a saved run (``covers-dist eval``).

:class:`PeriodicEvaluation` is what the driver uses when ``eval.every_iterations > 0``: in serial
mode a pass runs in place (deterministic); on Ray it runs in a background thread of the driver
that only waits on the evaluation actors and the clustering actor, so training goes on while the
pass runs; the driver collects the finished pass at its next iteration. Every pass is appended to
``RUN_DIR/eval.jsonl`` and its continual-learning metrics go into the next metrics row
(``eval/...``: metrics.jsonl, TensorBoard, the HTTP service, Prometheus).
"""

from __future__ import annotations

import threading
import time
import traceback
from pathlib import Path
from typing import Any, Callable

from ..config import Config
from ..envs.stream import TaskStream
from ..evaluation import append_pass, continual_metrics, eval_pairs, metric_row, read_passes, run_evaluation
from ..evaluation.protocol import oracle_policies

__all__ = ["evaluation_pass", "fresh_policy_weights", "PeriodicEvaluation", "group_progress"]


def group_progress(stream: TaskStream, episode_rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """{task: {"first_episode", "env_steps"}} from per-episode rows (``task``, ``episode_index``,
    ``length``): when each group first appeared and how many env steps were spent on it."""
    out: dict[str, dict[str, Any]] = {t: {"first_episode": None, "env_steps": 0} for t in stream.tasks}
    for row in episode_rows:
        info = out.get(row["task"])
        if info is None:
            continue
        idx = int(row["episode_index"])
        if info["first_episode"] is None or idx < info["first_episode"]:
            info["first_episode"] = idx
        info["env_steps"] += int(row["length"])
    return out


def fresh_policy_weights(cfg: Config, policy_id: int) -> tuple[int, Any]:
    """The initial weights training would give a new policy ``policy_id`` (its learner's seed),
    made without touching this process's random state; version -1 (never trained)."""
    import torch

    from ..envs import suite_layout
    from ..models import build_actor_critic
    from .learner import policy_seed

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(policy_seed(cfg.seed, policy_id))
        model = build_actor_critic(cfg.network, suite_layout(cfg.env.suite, cfg.env.image_size))
    return -1, model.get_weights()


def evaluation_pass(
    cfg: Config,
    executors: Any,
    stream: TaskStream,
    episodes_done: int,
    choose: Callable[[dict, list[int]], dict[str, Any]],
    confusion: dict[str, Any],
    weights_map: dict[int, tuple[int, Any]],
    info: dict[str, Any],
    tasks: list[str] | None = None,
    episodes: int | None = None,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """One pass over every (task, g) of ``tasks`` (default: ``eval.tasks`` or all), as a dict for eval.jsonl."""
    pairs = eval_pairs(stream, episodes_done, tasks if tasks is not None else cfg.eval.tasks)
    result = run_evaluation(
        executors,
        pairs,
        choose,
        oracle_policies(confusion),
        weights_map,
        cfg.seed,
        episodes or cfg.eval.episodes,
        modes=list(dict.fromkeys(cfg.eval.modes)),
        selections=list(dict.fromkeys(cfg.eval.selections)),
        log=log,
        new_policy=lambda pid: fresh_policy_weights(cfg, pid),
    )
    return {**info, "episodes": int(episodes_done), "seed": cfg.seed, "time_unix": time.time(), **result}


class PeriodicEvaluation:
    """Starts passes every ``eval.every_iterations`` iterations and hands back finished ones."""

    def __init__(self, cfg: Config, run_dir: Path, background: bool, log: Callable[[str], None] = print) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.background = background
        self.log = log
        self.passes = read_passes(self.run_dir)  # earlier passes of a resumed run
        self._thread: threading.Thread | None = None
        self._result: dict[str, Any] | None = None
        self._error: str | None = None
        self.last_iteration = self.passes[-1].get("iteration", -1) if self.passes else -1

    def rewind(self, iteration: int) -> None:
        """Forget passes after ``iteration`` (a resumed run repeats those iterations and re-evaluates)."""
        self.passes = [ev for ev in self.passes if ev.get("iteration", -1) <= iteration]
        self.last_iteration = self.passes[-1].get("iteration", -1) if self.passes else -1

    @property
    def enabled(self) -> bool:
        return self.cfg.eval.every_iterations > 0

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def due(self, iteration: int) -> bool:
        return self.enabled and iteration % self.cfg.eval.every_iterations == 0 and iteration != self.last_iteration

    def start(self, iteration: int, make_pass: Callable[[], dict[str, Any]]) -> None:
        """Run ``make_pass`` now (serial) or in a background thread (Ray); one pass at a time."""
        if self.running:
            self.log(f"evaluation at iteration {iteration} skipped: the previous pass is still running")
            return
        self.last_iteration = iteration
        if not self.background:
            self._result = make_pass()
            return

        def target() -> None:
            try:
                self._result = make_pass()
            except Exception:  # noqa: BLE001 - reported by collect(); training goes on
                self._error = traceback.format_exc(limit=4)

        self._thread = threading.Thread(target=target, name="covers-eval", daemon=True)
        self._thread.start()

    def collect(self, wait: bool = False) -> dict[str, float]:
        """Write a finished pass to eval.jsonl; returns its ``eval/...`` metrics ({} if none)."""
        if self._thread is not None:
            if wait:
                self._thread.join()
            if self._thread.is_alive():
                return {}
            self._thread = None
        if self._error is not None:
            self.log(f"warning: an evaluation pass failed and was skipped:\n{self._error}")
            self._error = None
        if self._result is None:
            return {}
        ev, self._result = self._result, None
        append_pass(self.run_dir, ev)
        self.passes.append(ev)
        cl = continual_metrics(self.passes)
        self.log(
            f"evaluation at iteration {ev.get('iteration')} ({ev['eval_episodes']} episodes from "
            f"{ev.get('distinct_initial_states', 'n/a')} initial states, "
            f"{ev['time_s']['total']:.0f} s): average success {_fmt(cl['average_success'])}, "
            f"zero-shot {_fmt(cl['zero_shot_success'])}, per group "
            + " ".join(f"{t}={_fmt(g['success'])}" for t, g in cl["groups"].items())
        )
        return metric_row(cl)


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}"
