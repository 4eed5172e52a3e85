"""Evaluation passes for a training run and for a saved run (``covers-dist eval``).

:class:`PeriodicEvaluation` is what the driver uses when ``eval.every_iterations > 0``: in serial
mode a pass runs in place (deterministic); on Ray it runs in a background thread of the driver
that only waits on the evaluation actors and the clustering actor, so training goes on while the
pass runs; the driver collects the finished pass at its next iteration. Every pass is appended to
``RUN_DIR/eval.jsonl`` and its continual-learning metrics go into the next metrics row
(``eval/...``: metrics.jsonl, TensorBoard, the HTTP service, Prometheus).
"""

from __future__ import annotations

import dataclasses
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..config import Config
from ..envs.stream import TaskStream
from ..evaluation.protocol import SPLITS
from ..evaluation import append_pass, continual_metrics, eval_pairs, metric_row, read_passes, run_evaluation
from ..evaluation.metrics import held_groups
from ..evaluation.protocol import oracle_policies

__all__ = [
    "evaluation_pass",
    "evaluate_saved_run",
    "SavedRunEvaluation",
    "fresh_policy_weights",
    "PeriodicEvaluation",
    "group_progress",
]


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
    split: str = "stop",
) -> dict[str, Any]:
    """One pass over every (task, g) of ``tasks`` (default: ``eval.tasks`` or all), as a dict for
    eval.jsonl; ``split``: ``stop`` for the passes of training (their initial states decide the
    stop), ``report`` for the run's report (``covers-dist eval``)."""
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
        split=split,
        frames_per_episode=cfg.clustering.initial_frames,
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
        self._finished: list[dict[str, Any]] = []  # passes done and not collected yet, oldest first
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

    def start_training_pass(
        self,
        backend: Any,
        stream: TaskStream,
        episodes_done: int,
        weights_map: dict[int, tuple[int, Any]],
        info: dict[str, Any],
    ) -> None:
        """Start a pass of a training run at iteration ``info["iteration"]``: the policies of
        ``weights_map`` act, chosen by the bank's what-if on each episode's first frames, on
        ``backend``'s evaluation executors; training's torch RNG is left as it was."""
        import torch

        confusion = backend.call_clustering("metrics").get("confusion", {})
        with torch.random.fork_rng(devices=[]):  # building the evaluation worker's model draws random numbers
            executors = backend.eval_executors()

        def choose(obs: dict[str, Any], groups: list[int]) -> dict[str, Any]:
            # only the policies of this pass's weights: on Ray, training goes on meanwhile and the bank
            # may hold a policy whose weights are not published yet
            return backend.call_clustering("what_if", obs, groups, sorted(weights_map))

        def make_pass() -> dict[str, Any]:
            return evaluation_pass(
                self.cfg, executors, stream, episodes_done, choose, confusion, weights_map, info, log=self.log
            )

        with torch.random.fork_rng(devices=[]):  # a serial pass runs here: training's torch RNG stays as it was
            self.start(int(info["iteration"]), make_pass)

    def start(self, iteration: int, make_pass: Callable[[], dict[str, Any]]) -> None:
        """Run ``make_pass`` now (serial) or in a background thread (Ray); one pass at a time."""
        if self.running:
            self.log(f"evaluation at iteration {iteration} skipped: the previous pass is still running")
            return
        self.last_iteration = iteration
        if not self.background:
            self._finished.append(make_pass())
            return

        def target() -> None:
            try:
                self._finished.append(make_pass())
            except Exception:  # noqa: BLE001 - reported by collect(); training goes on
                self._error = traceback.format_exc(limit=4)

        self._thread = threading.Thread(target=target, name="covers-eval", daemon=True)
        self._thread.start()

    def collect(self, wait: bool = False) -> dict[str, float]:
        """Write the passes finished since the last call to eval.jsonl (a pass that ended just before
        the next one started included); returns the newest one's ``eval/...`` metrics ({} if none)."""
        if self._thread is not None:
            if wait:
                self._thread.join()
            if not self._thread.is_alive():
                self._thread = None
        if self._error is not None:
            self.log(f"warning: an evaluation pass failed and was skipped:\n{self._error}")
            self._error = None
        row: dict[str, float] = {}
        while self._finished:
            ev = self._finished.pop(0)
            append_pass(self.run_dir, ev)
            self.passes.append(ev)
            cl = continual_metrics(self.passes)
            self.log(
                f"evaluation at iteration {ev.get('iteration')} ({ev['eval_episodes']} episodes from "
                f"{ev.get('distinct_initial_states', 'n/a')} initial states, "
                f"{ev['time_s']['total']:.0f} s): average success {_fmt(cl['average_success'])}, "
                f"zero-shot {_fmt(cl['zero_shot_success'])}, per group "
                + " ".join(
                    f"{t}={_fmt(g['success'])} (worst {_fmt(g['success_worst'])})" for t, g in cl["groups"].items()
                )
            )
            row = metric_row(cl)
        return row

    def stop_reason(self) -> str | None:
        """Why training should stop now under ``eval.stop_at`` (None: go on, or no rule): the groups
        held at the threshold over the last ``eval.held`` passes, once ``eval.stop_groups`` is met."""
        ev = self.cfg.eval
        if ev.stop_at is None or not self.passes:
            return None
        key = "greedy/agnostic" if "agnostic" in ev.selections else "greedy/oracle"
        held = held_groups(self.passes, ev.stop_at, ev.held, key)
        evaluated = list(dict.fromkeys(r["task"] for r in self.passes[-1]["pairs"]))
        if not held or (ev.stop_groups == "all" and set(held) != set(evaluated)):
            return None
        return (
            f"{', '.join(held)}: greedy success >= {ev.stop_at:g} on every (task, g) at {ev.held} "
            f"pass{'es' if ev.held > 1 else ''} in a row ({key}, eval.stop_at)"
        )


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}"


@dataclass(frozen=True)
class SavedRunEvaluation:
    """One evaluation pass of a saved run: the pass (a line of eval.jsonl), the continual-learning
    metrics over the run's passes up to it, and where it was written (None with ``write=False``)."""

    run_dir: Path
    checkpoint: str
    pass_: dict[str, Any]
    metrics: dict[str, Any]
    written: Path | None


def evaluate_saved_run(
    run_dir: str | Path,
    *,
    episodes: int,
    tasks: list[str] | None = None,
    modes: list[str] | None = None,
    selections: list[str] | None = None,
    workers: int = 0,
    split: str = "report",
    write: bool = True,
    log: Callable[[str], None] = print,
) -> SavedRunEvaluation:
    """Evaluate the newest valid checkpoint of ``run_dir`` on every (task, g) of ``tasks`` (default:
    every task of the run), read-only, with ``episodes`` episodes per pair, policy and mode.

    ``modes`` / ``selections`` replace the run's ``eval.modes`` / ``eval.selections``; ``workers``
    > 0 runs the episodes on that many Ray actors of a local, loopback-only Ray instance (0: in this
    process); ``split``: the initial states (``report``, never seen by the training passes, or
    ``stop``, theirs). The pass is appended to ``RUN_DIR/eval.jsonl`` unless ``write`` is False.
    Raises ``ValueError`` (a bad argument; ``ConfigError`` is one), ``FileNotFoundError`` or
    ``CheckpointError`` (no run, no valid checkpoint), each naming the problem.
    """
    from ..config import config_from_dict, config_to_dict
    from .saved_run import load_saved_run

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}, got {split!r}")
    saved = load_saved_run(run_dir, log=log)
    cfg = saved.cfg
    if tasks is not None:
        unknown = [t for t in tasks if t not in cfg.env.tasks]
        if unknown:
            raise ValueError(f"task(s) {unknown} were never part of this run; it trained on {list(cfg.env.tasks)}")
    data = config_to_dict(cfg)
    for key, value in (("modes", modes), ("selections", selections)):
        if value is not None:
            data["eval"][key] = list(value)
    if workers:
        data["eval"]["workers"] = workers
        data["eval"]["num_cpus"] = 1.0
    cfg = config_from_dict(data)  # checks the modes and selections
    stream = TaskStream.from_config(cfg.env, cfg.seed)
    episodes_done = int(saved.driver.get("next_episode", 0))
    groups = saved.driver.get("groups") or group_progress(stream, _episode_rows(saved.run_dir, episodes_done))
    info = {
        "iteration": int(saved.driver.get("iteration", 0)),
        "env_steps": int(saved.driver.get("env_steps", 0)),
        "source": f"checkpoint {saved.checkpoint.name}",
        "groups": groups,
    }
    service = saved.service
    executors, stop = _saved_run_executors(cfg, workers)
    try:
        ev = evaluation_pass(
            cfg,
            executors,
            stream,
            episodes_done,
            lambda obs, gids: service.what_if(obs, gids),
            service.metrics().get("confusion", {}),
            saved.weights_map,
            info,
            tasks=tasks,
            episodes=episodes,
            log=log,
            split=split,
        )
    finally:
        executors.close()
        stop()
    passes = read_passes(saved.run_dir)
    written = None
    if write:
        append_pass(saved.run_dir, ev)
        written = Path(saved.run_dir) / "eval.jsonl"
    history = [p for p in passes if p.get("iteration", -1) < ev["iteration"]] + [ev]
    return SavedRunEvaluation(Path(saved.run_dir), saved.checkpoint.name, ev, continual_metrics(history), written)


def _episode_rows(run_dir: Path, episodes_done: int) -> list[dict[str, Any]]:
    """Rows of episodes.jsonl and its rotated segments before ``episodes_done`` (newest per index);
    [] if there are none."""
    from .logfiles import read_jsonl_segments

    rows: dict[int, dict[str, Any]] = {}
    for row in read_jsonl_segments(run_dir, "episodes.jsonl", strict=False):
        if int(row.get("episode_index", -1)) in range(episodes_done):
            rows[int(row["episode_index"])] = row
    return [rows[i] for i in sorted(rows)]


def _saved_run_executors(cfg: Config, workers: int) -> tuple[Any, Callable[[], None]]:
    """(executors, stop function): one worker in this process, or Ray actors on a local instance."""
    if workers == 0:
        from ..evaluation import LocalExecutors
        from .rollout import EVAL_WORKER_INDEX, RolloutWorker

        return LocalExecutors([RolloutWorker(cfg, EVAL_WORKER_INDEX)]), lambda: None
    from .backends import RayEvalExecutors
    from .ray_setup import init_ray, shutdown_ray

    init_ray(max(cfg.runtime.num_cpus, workers), cfg.runtime.ray_address)
    local = dataclasses.replace(cfg, runtime=dataclasses.replace(cfg.runtime, serial=False))
    return RayEvalExecutors(local), shutdown_ray
