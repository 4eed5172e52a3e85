"""The driver: Algorithm 1 of COVERS, one iteration per call of :meth:`Trainer.step`.

Each iteration handles the next ``clustering.update_every`` (Nu) episodes of the task stream, in
named, timed phases (``time/<phase>`` in metrics.jsonl):

1. ``sample``: the rollout workers run them with the current policy (the stream's true task and
   symmetry pick the environment; the policy is not told);
2. ``assign``: the clustering service compares the episodes' first-k observations with every
   policy's buffer and recalls a policy or creates a new one;
3. ``update_submit`` / ``update_wait``: the assigned policy's learner runs PPO on the episodes
   (with the behaviour log-probs stored in them); the new weights are published under a new
   version, and workers and the clustering service pull them when the version changed;
4. ``record``: the episodes go to the clustering service's history (assignments, ARI).

What is not the algorithm lives beside it: weight versions and the update in flight
(:mod:`.weights`), per-group counts and the metrics row (:mod:`.tally`), checkpoints
(:mod:`.trainer_checkpoint`), periodic evaluation (:mod:`.evaluation`). Checkpoints are written
every ``runtime.checkpoint_every`` iterations and on SIGINT/SIGTERM; ``resume=True`` continues
from the newest valid checkpoint of the run directory.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import signal
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import yaml

from ..config import Config, config_to_dict, load_run_config
from ..envs.stream import TaskStream
from ..ppo.noise import faded_beta
from ..results.provenance import record_start
from ..storage import Storage, StorageError, is_uri, redact_uri
from .checkpoint import latest_valid_checkpoint
from .clustering_service import SINGLE_POLICY_METHODS
from .evaluation import PeriodicEvaluation
from .lease import LeaseHeld, RunLease
from .logfiles import remove_log
from .metrics import MetricsWriter, Progress
from .processes import announce
from .ray_setup import check_run_dir_outlives_the_job
from .rollout import EpisodeSpec
from .run_storage import CHECKPOINTS, CLUSTERING_LIVE, LEARNERS_LIVE, PROCESSES
from .run_storage import clear_storage, drop_live_state, fetch_run, run_store, storage_holds_a_run, storage_location
from .tally import EpisodeTally, iteration_row
from .trainer_checkpoint import restore_trainer, save_trainer
from .weights import PolicyWeights

__all__ = ["Trainer", "train", "holds_a_run", "take_lease", "LeaseHeld"]


class Trainer:
    """Runs COVERS (or a baseline variant) on the serial or the Ray backend."""

    def __init__(
        self, cfg: Config, resume: bool = False, log: Callable[[str], None] = print, lease: RunLease | None = None
    ) -> None:
        self.cfg = cfg
        self.log = log
        self.run_dir = Path(cfg.runtime.run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        # one writer per run: the lease comes first (train() takes it before clearing an old run)
        self.lease = lease if lease is not None else take_lease(cfg, log)
        try:
            self._setup(cfg, resume)
        except BaseException:
            self.lease.release()
            raise

    def _setup(self, cfg: Config, resume: bool) -> None:
        self.stream = TaskStream(
            list(cfg.env.tasks), cfg.env.group, cfg.env.episodes_per_task, cfg.env.held_out, cfg.seed
        )
        self.iteration = 0
        self.next_episode = 0
        self.env_steps = 0
        self.current_policy = 0
        self.tally = EpisodeTally(list(cfg.env.tasks))
        self.noise_beta = cfg.ppo.noise_beta  # the colour the latest batch was sampled with
        self.phase_time: dict[str, float] = {}
        self.clock_start, self.clock_steps = time.monotonic(), 0  # for env steps per second
        self.on_iteration: list[Callable[[], None]] = []  # called after every iteration (e.g. service checks)
        self._stop = False
        self._resume_from: Path | None = None
        if resume:
            fetch_run(cfg, log=self.log)  # a driver on a fresh node: the newest checkpoint from the storage
            self._resume_from = latest_valid_checkpoint(self.run_dir, log=self.log)
            if self._resume_from is None:
                raise FileNotFoundError(f"no valid checkpoint to resume from in {self.run_dir}/checkpoints")
        else:  # a new run: live states left by an earlier run in this storage are not this run's
            drop_live_state(cfg)
        if cfg.runtime.serial:
            from .backends import SerialBackend

            self.backend: Any = SerialBackend(cfg, self.run_dir)
        else:
            from .backends import RayBackend

            self.backend = RayBackend(cfg, self.run_dir)
        self.weights = PolicyWeights(
            self.backend, single_policy=cfg.runtime.method in SINGLE_POLICY_METHODS, learner_ahead=cfg.runtime.learner_ahead
        )
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
        record_start(self.run_dir, resumed=resume)  # the code's commit and the CPU, for result files
        self.evaluation = PeriodicEvaluation(cfg, self.run_dir, background=not cfg.runtime.serial, log=self.log)

    # ---- Algorithm 1 -------------------------------------------------------------------------
    def step(self) -> dict[str, Any]:
        """One iteration of Algorithm 1 over the next Nu episodes of the stream; its metrics row.

        sample -> assign -> update -> record. With ``clustering.assign_at: reset`` the assignment
        comes first, from the episodes' first frames, and the assigned policy acts. Pipelined
        (``runtime.pipeline``), the update submitted by the previous iteration finishes while this
        one samples and is published before this assignment; this iteration's update is left
        running, and the row reports the previous update's statistics (docs/guide/runtime.md,
        "Pipelining").
        """
        plan = self._plan()  # which task and transform each worker runs: the policy is not told
        assign_first = self.cfg.clustering.assign_at == "reset"
        acting, record = self.current_policy, {}
        if assign_first:
            with self._phase("assign"):
                record = self._assign(self.backend.first_frames(plan), _in_order(plan))
            acting = int(record["policy_id"])
        with self._phase("sample"):
            firsts, summaries, episodes = self._sample(plan, acting)
        stats: dict[str, Any] = {}
        if self.weights.pending is not None:  # pipelined: the previous update ran beside the sampling
            with self._phase("update_wait"):
                stats = self.weights.finish_update()
        if not assign_first:
            with self._phase("assign"):
                record = self._assign(_stacked(firsts), summaries)
        policy = int(record["policy_id"])
        with self._phase("update_submit"):  # the serial backend runs the update here
            self.weights.submit_update(policy, episodes, self.iteration + 1)  # this iteration's row number
        if not self.cfg.runtime.pipeline:
            with self._phase("update_wait"):
                stats = self.weights.finish_update()
        with self._phase("record"):
            self._record(summaries, policy)
        return iteration_row(self, record, stats, self.backend.call_clustering("metrics"))

    def _plan(self) -> list[list[EpisodeSpec]]:
        """The next Nu episodes of the stream, dealt to the rollout workers in turn."""
        specs = []
        for i in range(self.next_episode, self.next_episode + self.cfg.clustering.update_every):
            t = self.stream.task_at(i)
            specs.append(EpisodeSpec(i, t.task, t.g.name, t.group_id))
        n = self.cfg.runtime.num_workers
        return [specs[w::n] for w in range(n)]

    def _sample(self, plan: list[list[EpisodeSpec]], policy_id: int) -> tuple[list[dict], list, Any]:
        """Run the plan with ``policy_id``'s published weights: the episodes' first frames and their
        summaries (both in episode order) and the episodes for the learner."""
        version, handle = self.weights.versions[policy_id], self.weights.handles[policy_id]
        self.noise_beta = self.policy_noise_beta(policy_id)
        firsts, summaries, episodes = self.backend.collect_sample(
            self.backend.submit_sample(plan, policy_id, version, handle, self.noise_beta)
        )
        order = sorted(range(len(summaries)), key=lambda i: summaries[i]["episode_index"])
        return [firsts[i] for i in order], [summaries[i] for i in order], episodes

    def policy_noise_beta(self, policy_id: int) -> float:
        """The colour of ``policy_id``'s training noise: ``ppo.noise_beta``, faded by its own recent
        success when ``ppo.noise_fade_success`` is set (:func:`~covers_dist.ppo.noise.faded_beta`)."""
        ppo = self.cfg.ppo
        return faded_beta(ppo.noise_beta, ppo.noise_fade_success, self.tally.policy_success.get(policy_id, []))

    def _assign(self, obs: dict[str, np.ndarray], episodes: list[Any]) -> dict[str, Any]:
        """The clustering service's assignment of a batch (episode specs or summaries, in order);
        a policy it creates gets its learner and published weights at once."""
        indices = [int(_field(e, "episode_index")) for e in episodes]
        groups = [int(_field(e, "group_id")) for e in episodes]
        record = self.backend.call_clustering("assign", self.iteration, obs, indices, groups, self.weights.published())
        if int(record["policy_id"]) not in self.weights.versions:
            self.start_policy(int(record["policy_id"]))
        return record

    def _record(self, summaries: list[dict[str, Any]], policy: int) -> None:
        """Count the batch, hand it to the clustering service's history, advance the counters."""
        self.tally.record(summaries, policy)
        self.backend.call_clustering("record_episodes", summaries)
        self.current_policy = policy
        self.next_episode += len(summaries)
        self.env_steps += sum(s["length"] for s in summaries)
        self.iteration += 1

    @contextmanager
    def _phase(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        yield
        self.phase_time[name] = time.perf_counter() - t0

    # ---- policies and weights ------------------------------------------------------------------
    def start_policy(self, policy_id: int) -> None:
        """Give policy ``policy_id`` its learner and publish its initial weights (the loop does this
        for policy 0 when it starts, and for every policy the bank creates)."""
        self.weights.start_policy(policy_id)

    def newest_weights(self) -> dict[int, tuple[int, Any]]:
        """Every policy's newest weights, the update in flight included (what evaluation acts with)."""
        return self.weights.newest()

    def drain(self) -> dict[str, Any]:
        """Finish and publish the update still in flight (pipelined loop); its statistics ({} if none)."""
        return self.weights.finish_update()

    def checkpoint(self) -> Path:
        """Write a checkpoint (:mod:`.trainer_checkpoint`); its path."""
        return save_trainer(self)

    # ---- the loop ------------------------------------------------------------------------------
    def _on_signal(self, signum: int, _frame: Any) -> None:
        self.log(f"received signal {signum}: checkpointing after this iteration")
        self._stop = True

    def run(self) -> dict[str, Any]:
        """Step until ``runtime.total_env_steps``, ``runtime.time_limit_minutes``, ``eval.stop_at``
        or a signal: log, evaluate and checkpoint on schedule, then (unless a signal ended it) a final
        evaluation pass, and a checkpoint."""
        old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        resumed_at = None
        if self._resume_from is not None:  # rows of iterations after the checkpoint are redone: drop them
            resumed_at = int(json.loads((self._resume_from / "driver.json").read_text())["iteration"])
        rt = self.cfg.runtime
        writer = MetricsWriter(self.run_dir, resume_iteration=resumed_at, rotate_mb=rt.log_rotate_mb, keep=rt.log_keep)
        try:
            if self._resume_from is not None:
                restore_trainer(self, self._resume_from)
            else:
                self.start_policy(0)
            announce(storage_location(self.cfg), "driver")  # recorded once the loop runs
            self.clock_start, self.clock_steps = time.monotonic(), self.env_steps
            deadline = None if rt.time_limit_minutes is None else self.clock_start + 60.0 * rt.time_limit_minutes
            progress = Progress(rt.total_env_steps, rt.log_every_s, self.env_steps, deadline=deadline)
            row: dict[str, Any] = {}
            # why the loop ends before total_env_steps; a resumed run that met eval.stop_at stops at
            # once, a time limit only after an iteration (however short the limit, a run does one)
            reason = self._early_stop(None)
            while self.env_steps < rt.total_env_steps and not self._stop and reason is None:
                self.lease.check()  # another driver took the run over: stop before writing on
                row = self.step()
                if self.evaluation.due(self.iteration):
                    self.start_evaluation()
                row.update(self.evaluation.collect())
                self.backend.call_clustering("report", row)
                self.write_iteration(writer, row)
                progress.maybe_print(row)
                for hook in self.on_iteration:
                    hook()
                if self.iteration % rt.checkpoint_every == 0:
                    self.checkpoint()
                reason = self._early_stop(deadline)
            if row and self.evaluation.enabled and not self._stop:  # a final pass, unless interrupted
                final = self.evaluation.collect(wait=True)  # a pass still running in the background
                if self.evaluation.last_iteration != self.iteration:
                    self.start_evaluation()
                    final.update(self.evaluation.collect(wait=True))
                if final:  # the iteration's row again, now with the pass's metrics (plots keep the last)
                    row.update(final)
                    self.backend.call_clustering("report", row)
                    writer.scalars(row)
            self.lease.check()
            path = self.checkpoint()
            if row:
                progress.maybe_print(row, force=True)
            status = "interrupted" if self._stop else "finished"
            self.log(f"{status}: checkpoint {path}; resume with: covers-dist train --resume {self.run_dir}")
            out = {"status": status, "row": row, "checkpoint": str(path), **self.backend.call_clustering("metrics")}
            return {**out, "stopped_early": reason} if reason is not None else out
        except (StorageError, OSError) as e:  # an outage past its retries, a full disk: stop, keep what is valid
            return self._storage_fault(e)
        finally:
            try:
                writer.close()
            except OSError as e:  # a full disk: the logs keep what was written; a resume drops the rest
                self.log(f"warning: the logs could not be closed ({type(e).__name__}: {e})")
            for s, h in old.items():
                signal.signal(s, h)

    def _storage_fault(self, error: BaseException) -> dict[str, Any]:
        """Stop on a storage fault without writing on: nothing after the newest valid checkpoint is
        kept, and a resume from it (once the storage is back) ends where an unbroken run ends."""
        self._stop = True
        ckpt = latest_valid_checkpoint(self.run_dir, log=self.log)
        message = f"{type(error).__name__}: {error}".splitlines()[0]
        where = f"its last valid checkpoint is {ckpt}" if ckpt is not None else "it has no valid checkpoint yet"
        self.log(
            f"stopped by a storage fault at iteration {self.iteration} ({message}); {where}. Once the storage "
            f"is back (or the disk has room): covers-dist train --resume {self.run_dir}"
        )
        return {"status": "storage-fault", "error": message, "checkpoint": None if ckpt is None else str(ckpt)}

    def _early_stop(self, deadline: float | None) -> str | None:
        """Why the loop ends before ``runtime.total_env_steps`` (None: it goes on): groups held under
        ``eval.stop_at``, or ``runtime.time_limit_minutes`` reached (``deadline``, monotonic clock)."""
        rt = self.cfg.runtime
        if self.env_steps >= rt.total_env_steps:
            return None
        reason = self.evaluation.stop_reason()
        if reason is None and deadline is not None and time.monotonic() >= deadline:
            reason = f"the time limit of {rt.time_limit_minutes:g} min (runtime.time_limit_minutes)"
        if reason is not None:
            self.log(f"stopping at {self.env_steps} env steps: {reason}")
        return reason

    def start_evaluation(self) -> None:
        """Evaluate every (task, g) with the bank as it is now (serial: in place; Ray: in the background)."""
        info = {
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "source": "training",
            "groups": {t: dict(v) for t, v in self.tally.groups.items()},
        }
        self.evaluation.start_training_pass(self.backend, self.stream, self.next_episode, self.newest_weights(), info)

    def write_iteration(self, writer: Any, row: dict[str, Any]) -> None:
        """Log the iteration just stepped: its metrics row and its episodes (a ``MetricsWriter``)."""
        writer.scalars(row)
        writer.episodes(self.tally.episode_rows(self.env_steps, self.iteration))

    def close(self) -> None:
        try:
            self.backend.shutdown()
        finally:
            self.lease.release()


def _stacked(firsts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Per-episode first frames as one batch (only the assignment after sampling needs them)."""
    return {key: np.concatenate([f[key] for f in firsts]) for key in ("image", "proprio")}


def _in_order(plan: list[list[EpisodeSpec]]) -> list[EpisodeSpec]:
    return sorted((s for part in plan for s in part), key=lambda s: s.episode_index)


def _field(item: Any, name: str) -> Any:
    return item[name] if isinstance(item, dict) else getattr(item, name)


def take_lease(cfg: Config, log: Callable[[str], None] = print) -> RunLease:
    """This driver's lease on the run of ``cfg`` (:mod:`covers_dist.runtime.lease`); raises
    :class:`LeaseHeld` naming the driver that holds it."""
    return RunLease(run_store(cfg), cfg.runtime.lease_ttl_s, log=log).acquire()


def holds_a_run(cfg: Config) -> bool:
    """Whether the run directory or the storage of ``cfg`` holds a run's checkpoints (a new run
    there needs ``overwrite``)."""
    ckpts = Path(cfg.runtime.run_dir) / "checkpoints"
    return (ckpts.is_dir() and any(ckpts.iterdir())) or storage_holds_a_run(cfg)


def _run_config(resume_dir: str) -> Config:
    """The saved config of the run to resume: ``RUN_DIR/config.yaml``, or, for a storage URI
    (``--resume s3://bucket/run``), the storage's copy (the run directory it names is then
    filled from the storage)."""
    if is_uri(resume_dir):
        try:
            text = Storage(resume_dir).read_bytes("config.yaml")
        except StorageError as e:
            raise FileNotFoundError(f"{redact_uri(resume_dir.split('?', 1)[0])} holds no run to resume ({e})") from e
        with tempfile.NamedTemporaryFile("wb", suffix=".yaml") as fh:
            fh.write(text)
            fh.flush()
            return load_run_config(fh.name)
    cfg_path = Path(resume_dir) / "config.yaml"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{resume_dir} is not a run directory (no config.yaml)")
    return load_run_config(cfg_path)


def rooted_at(cfg: Config, resume_dir: str, log: Callable[[str], None] = print) -> Config:
    """The saved config of the run in ``resume_dir`` with that directory as its run directory.

    A run directory may have been moved or copied since it was saved: it is resumed where it is now,
    never into the ``runtime.run_dir`` its config.yaml names (which may be the original's). A local
    storage inside the old run directory moves along with it; a storage elsewhere (a URI, or a path
    outside) is the run's own state and is kept, with a note in the log.
    """
    if is_uri(resume_dir):
        return cfg  # resumed from its storage: the run directory its config names is filled from there
    here, saved = Path(resume_dir).resolve(), Path(cfg.runtime.run_dir).resolve()
    if here == saved:
        return cfg
    storage = cfg.runtime.storage
    if storage and not is_uri(storage):
        local = Path(storage).resolve()
        if local == saved or saved in local.parents:
            storage = str(here / local.relative_to(saved))
        else:
            log(f"note: {resume_dir} was saved as {saved}; it keeps its storage {storage}")
    elif storage:
        log(f"note: {resume_dir} was saved as {saved}; it keeps its storage {redact_uri(storage)}")
    runtime = dataclasses.replace(cfg.runtime, run_dir=str(here), storage=storage)
    return dataclasses.replace(cfg, runtime=runtime)


def train(
    cfg: Config | None = None,
    resume_dir: str | None = None,
    log: Callable[[str], None] = print,
    overwrite: bool = False,
    services: Callable[[Config, Any], Any] | None = None,
) -> dict:
    """Run training to the end (or resume ``resume_dir``); starts Ray when the config asks for it.

    A new run refuses a run directory that already holds checkpoints unless ``overwrite``.
    ``services(cfg, clustering)``: started next to training (the command that runs training
    passes the HTTP service); it returns None or an object with ``stop()`` and, optionally,
    ``check()``, which is called after every iteration (to restart what stopped).
    """
    if resume_dir is not None:
        cfg = rooted_at(_run_config(resume_dir), resume_dir, log)
    assert cfg is not None
    check_run_dir_outlives_the_job(cfg.runtime.run_dir)
    lease = take_lease(cfg, log)  # before anything of the run is read, cleared or written
    try:
        return _train(cfg, resume_dir, lease, log, overwrite, services)
    finally:
        lease.release()  # the trainer gave it back already, unless it never started


def _train(
    cfg: Config,
    resume_dir: str | None,
    lease: RunLease,
    log: Callable[[str], None],
    overwrite: bool,
    services: Callable[[Config, Any], Any] | None,
) -> dict:
    run_dir = Path(cfg.runtime.run_dir)
    if resume_dir is None and holds_a_run(cfg):
        if not overwrite:
            storage = redact_uri(cfg.runtime.storage.split("?", 1)[0]) if cfg.runtime.storage else None
            where = f"{run_dir} (storage {storage})" if storage else str(run_dir)
            raise FileExistsError(
                f"{where} already holds a run: continue it with --resume {run_dir}, "
                "choose another --run-dir, or pass --overwrite to start over"
            )
        clear_storage(cfg)
        for name in (CHECKPOINTS, LEARNERS_LIVE, CLUSTERING_LIVE, PROCESSES, "tb"):
            shutil.rmtree(run_dir / name, ignore_errors=True)
        for name in ("metrics.jsonl", "episodes.jsonl", "eval.jsonl"):
            remove_log(run_dir, name)  # with its rotated segments
    # SIGINT/SIGTERM at any moment, start-up and shut-down included, ends the run gracefully: before
    # the loop it stops it before its first iteration, in the loop after the iteration in flight
    # (Trainer.run's own handler), after it nothing is cut short
    # (while Ray itself starts, its own handler ends the process: there is nothing to save yet)
    signals: list[int] = []

    def graceful() -> dict[int, Any]:
        return {s: signal.signal(s, lambda signum, _frame: signals.append(signum)) for s in (signal.SIGINT, signal.SIGTERM)}

    original = graceful()
    started = False
    trainer = service = None
    try:
        if not cfg.runtime.serial:
            from .ray_setup import init_ray, shutdown_ray

            init_ray(cfg.runtime.num_cpus, cfg.runtime.ray_address)  # a local instance counts the machine's GPUs
            started = True
            graceful()  # ray.init replaced it with one that exits at once
        trainer = Trainer(cfg, resume=resume_dir is not None, log=log, lease=lease)
        if services is not None:
            service = services(cfg, trainer.backend.clustering)
            if service is not None and callable(getattr(service, "check", None)):
                trainer.on_iteration.append(service.check)
        if signals:
            trainer._on_signal(signals[0], None)
        return trainer.run()
    finally:
        if service is not None:
            service.stop()
        if trainer is not None:
            trainer.close()
        if started and (kept := shutdown_ray()):  # kept after a failure
            log(f"Ray's logs of this run are kept in {kept}")
        for s, h in original.items():
            signal.signal(s, h)
