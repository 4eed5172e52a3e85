"""The driver: Algorithm 1 of COVERS as a loop of named, timed phases.

Each iteration handles the next ``clustering.update_every`` (Nu) episodes of the task stream:

1. ``sample``: the rollout workers run them with the current policy (the stream's true task and
   symmetry pick the environment; the policy is not told);
2. ``assign``: the clustering actor compares the episodes' first-k observations with every
   policy's buffer and recalls a policy or creates a new one;
3. ``update``: the assigned policy's learner runs PPO on the episodes (with the behaviour
   log-probs stored in them);
4. ``publish``: the new weights go to the object store with a new version; workers and the
   clustering actor pull them only when the version changed.

Checkpoints are written every ``runtime.checkpoint_every`` iterations and on SIGINT/SIGTERM;
``resume=True`` continues from the newest valid checkpoint of the run directory.
"""

from __future__ import annotations

import json
import shutil
import signal
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch
import yaml

from ..config import Config, config_to_dict, load_run_config
from ..envs.stream import TaskStream
from .checkpoint import latest_valid_checkpoint, write_checkpoint
from .clustering_service import LIVE_DIR as CLUSTERING_LIVE_DIR
from .evaluation import PeriodicEvaluation, evaluation_pass
from .learner import LIVE_DIR, live_state_path
from .logfiles import remove_log
from .metrics import M, MetricsWriter, Progress
from .processes import announce
from .ray_setup import resolve_weights
from .rollout import EpisodeSpec
from .saved_run import probe_mismatch

__all__ = ["Trainer", "train"]



class Trainer:
    """Runs COVERS (or a baseline variant) on the serial or the Ray backend."""

    def __init__(self, cfg: Config, resume: bool = False, log: Callable[[str], None] = print) -> None:
        self.cfg = cfg
        self.log = log
        self.run_dir = Path(cfg.runtime.run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.stream = TaskStream(
            list(cfg.env.tasks), cfg.env.group, cfg.env.episodes_per_task, cfg.env.held_out, cfg.seed
        )
        self.iteration = 0
        self.next_episode = 0
        self.env_steps = 0
        self.acted_other = 0  # episodes acted by a policy other than the one they were assigned to
        self.current_policy = 0
        self.weight_version = 0
        self.versions: dict[int, int] = {}
        self.learner_versions: dict[int, int] = {}  # each learner's version once its submitted updates are done
        self.handles: dict[int, Any] = {}
        self.success: dict[str, float] = {}
        self.returns: dict[str, float] = {}
        self.phase_time: dict[str, float] = {}
        # per task group: first episode index and env steps spent on it (for evaluation metrics)
        self.group_info: dict[str, dict[str, Any]] = {t: {"first_episode": None, "env_steps": 0} for t in cfg.env.tasks}
        self._stop = False
        self._last_rows: list[dict[str, Any]] = []
        self._t_start, self._steps_at_start = time.monotonic(), 0
        self._resume_from: Path | None = None
        self._pending_update: tuple[int, Any] | None = None  # (policy id, submitted or _Completed update)
        self.on_iteration: list[Callable[[], None]] = []  # called after every iteration (e.g. service checks)
        if resume:
            self._resume_from = latest_valid_checkpoint(self.run_dir, log=self.log)
            if self._resume_from is None:
                raise FileNotFoundError(f"no valid checkpoint to resume from in {self.run_dir}/checkpoints")
        else:  # a new run: live states left by an earlier run in this directory are not this run's
            _drop_live_states(self.run_dir)
            shutil.rmtree(self.run_dir / CLUSTERING_LIVE_DIR, ignore_errors=True)
        if cfg.runtime.serial:
            from .backends import SerialBackend

            self.backend: Any = SerialBackend(cfg, self.run_dir)
        else:
            from .backends import RayBackend

            self.backend = RayBackend(cfg, self.run_dir)
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
        self.evaluation = PeriodicEvaluation(cfg, self.run_dir, background=not cfg.runtime.serial, log=self.log)

    # ---- phases --------------------------------------------------------------------------------
    @contextmanager
    def _phase(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        yield
        self.phase_time[name] = time.perf_counter() - t0

    def _plan(self) -> list[list[EpisodeSpec]]:
        nu = self.cfg.clustering.update_every
        specs = []
        for i in range(self.next_episode, self.next_episode + nu):
            t = self.stream.task_at(i)
            specs.append(EpisodeSpec(i, t.task, t.g.name, t.group_id))
        n = self.cfg.runtime.num_workers
        return [specs[w::n] for w in range(n)]

    def _collect(self, pending: Any) -> tuple[list, list, Any]:
        """A submitted sample's first frames and summaries, in episode order, and its episodes."""
        firsts, summaries, episodes = self.backend.collect_sample(pending)
        order = sorted(range(len(summaries)), key=lambda i: summaries[i]["episode_index"])
        return [firsts[i] for i in order], [summaries[i] for i in order], episodes

    def _assign(self, obs: dict[str, np.ndarray], episodes: list[Any]) -> dict[str, Any]:
        """The clustering actor's assignment of a batch (episode specs or summaries, in order);
        a policy it creates gets its learner and published weights at once."""
        indices = [int(_field(e, "episode_index")) for e in episodes]
        groups = [int(_field(e, "group_id")) for e in episodes]
        weights_map = {pid: (self.versions[pid], self.handles[pid]) for pid in self.versions}
        record = self.backend.call_clustering("assign", self.iteration, obs, indices, groups, weights_map)
        if int(record["policy_id"]) not in self.versions:
            self._new_policy(int(record["policy_id"]))
        return record

    def _publish(self, policy_id: int, weights: Any) -> None:
        """New weights (a state dict) to the object store under a new version."""
        self._publish_handle(policy_id, self.backend.publish(weights))

    def _publish_handle(self, policy_id: int, handle: Any) -> None:
        """Weights already in the object store get a new version; the clustering service (features,
        the HTTP service's act) loads them now, workers when they next sample with them."""
        self.weight_version += 1
        self.versions[policy_id] = self.weight_version
        self.handles[policy_id] = handle
        self.backend.call_clustering("sync_weights", {policy_id: (self.weight_version, handle)})

    def _new_policy(self, policy_id: int) -> None:
        self.backend.ensure_learner(policy_id)
        self.learner_versions[policy_id], weights = self.backend.call_learner(policy_id, "weights")
        self._publish(policy_id, weights)
        self._prepare_next_learner()

    def _prepare_next_learner(self) -> None:
        """Start the next policy's learner ahead of time (the bank numbers policies 0, 1, 2, ...),
        unless the method keeps a single policy."""
        if self.cfg.runtime.method not in ("equi", "cnn"):
            self.backend.prepare_learner(max(self.versions) + 1)

    def _complete_pending(self) -> tuple[int, dict[str, Any], Any] | None:
        """Wait for the submitted update (if any) without publishing it: (policy, statistics, weights handle)."""
        if self._pending_update is None:
            return None
        policy_id, pending = self._pending_update
        if not isinstance(pending, _Completed):
            pending = _Completed(*self.backend.collect_update(pending))
            self._pending_update = (policy_id, pending)
        return policy_id, pending.stats, pending.handle

    def _finish_update(self) -> dict[str, Any]:
        """Wait for the submitted update (if any) and publish its weights; its statistics."""
        done = self._complete_pending()
        if done is None:
            return {}
        self._pending_update = None
        policy_id, stats, handle = done
        self._publish_handle(policy_id, handle)
        return stats

    def newest_weights(self) -> dict[int, tuple[int, Any]]:
        """``{policy id: (version, handle)}`` of every policy's newest weights, the update still in
        flight included: it is waited for but not published, so training's schedule is unchanged
        (its version is negative: never one that workers hold). What evaluation acts with."""
        weights_map = {pid: (self.versions[pid], self.handles[pid]) for pid in self.versions}
        done = self._complete_pending()
        if done is not None:
            weights_map[done[0]] = (-(self.weight_version + 1), done[2])
        return weights_map

    def drain(self) -> dict[str, Any]:
        """Finish and publish the update still in flight (pipelined loop); its statistics ({} if none)."""
        return self._finish_update()

    def step(self) -> dict[str, Any]:
        """One iteration; returns the metrics row.

        Sequential (``runtime.pipeline: false``): sample -> assign -> update -> publish
        (``clustering.assign_at: reset``: assign -> sample -> update -> publish). Pipelined: this
        iteration's sampling runs while the previous iteration's update finishes; those weights are
        published before this iteration's assignment, and this iteration's update is submitted and
        left running (the row reports the previous update's statistics). Sampling therefore uses
        the sampling policy's weights from one update earlier (docs/runtime.md, "Pipelining").
        """
        plan = self._plan()
        reset = self.cfg.clustering.assign_at == "reset"
        record: dict[str, Any] = {}
        if reset:
            with self._phase("assign"):  # from the first frames, before anything acts
                specs = sorted((s for part in plan for s in part), key=lambda s: s.episode_index)
                record = self._assign(self.backend.first_frames(plan), specs)
            sampler = int(record["policy_id"])
        else:
            sampler = self.current_policy
        t0 = time.perf_counter()
        pending = self.backend.submit_sample(plan, sampler, self.versions[sampler], self.handles[sampler])
        firsts, summaries, episodes = self._collect(pending)
        self.phase_time["sample"] = time.perf_counter() - t0
        stats: dict[str, Any] = {}
        if self._pending_update is not None:  # pipelined: the previous update ran alongside the sampling
            stats = self._finish_update()
            self.phase_time["update"] = time.perf_counter() - t0
        if not reset:
            obs = {
                "image": np.concatenate([f["image"] for f in firsts]),
                "proprio": np.concatenate([f["proprio"] for f in firsts]),
            }
            with self._phase("assign"):
                record = self._assign(obs, summaries)
        chosen = int(record["policy_id"])
        with self._phase("submit"):  # serial backend: the update itself runs here
            base = self.learner_versions[chosen]  # a retried update from this version is applied once
            self._pending_update = (chosen, self.backend.submit_update(chosen, episodes, base))
            self.learner_versions[chosen] = base + 1
        if not self.cfg.runtime.pipeline:
            with self._phase("update"):
                stats = self._finish_update()
        with self._phase("publish"):
            for s in summaries:
                s["assigned_policy"] = chosen
                self.acted_other += int(s["policy_id"] != chosen)
            self.backend.call_clustering("record_episodes", summaries)
        self._last_rows = summaries
        self.current_policy = chosen
        self.next_episode += len(summaries)
        self.env_steps += sum(s["length"] for s in summaries)
        self.iteration += 1
        batch_success: dict[str, list[float]] = {}
        batch_return: dict[str, list[float]] = {}
        for s in summaries:
            info = self.group_info.setdefault(s["task"], {"first_episode": None, "env_steps": 0})
            if info["first_episode"] is None:
                info["first_episode"] = int(s["episode_index"])
            info["env_steps"] += int(s["length"])
            batch_success.setdefault(s["task"], []).append(s["success"])
            batch_return.setdefault(s["task"], []).append(s["return"])
        for task in batch_success:  # the latest batch of each task group seen so far
            self.success[task] = float(np.mean(batch_success[task]))
            self.returns[task] = float(np.mean(batch_return[task]))
        return self._row(record, stats)

    def _row(self, record: dict[str, Any], stats: dict[str, Any]) -> dict[str, Any]:
        metrics = self.backend.call_clustering("metrics")
        dists = [d for d in record.get("distances", {}).values() if d is not None]
        row: dict[str, Any] = {
            M.ITERATION: self.iteration,
            M.EPISODES: self.next_episode,
            M.ENV_STEPS: self.env_steps,
            M.POLICY: self.current_policy,
            M.NUM_POLICIES: metrics.get("num_policies", len(self.versions)),
            M.ARI: metrics.get("ari", float("nan")),
            M.NEW_POLICY: bool(record.get("new", False)),
            M.WRONG_POLICY: self.acted_other / max(self.next_episode, 1),
            M.DISTANCE_MIN: min(dists) if dists else float("nan"),
            M.STEPS_PER_S: (self.env_steps - self._steps_at_start) / max(time.monotonic() - self._t_start, 1e-9),
            "wall_time": time.time(),
        }
        for task in self.success:
            row[f"{M.SUCCESS}/{task}"] = self.success[task]
            row[f"{M.RETURN}/{task}"] = self.returns[task]
        for name, secs in self.phase_time.items():
            row[f"{M.TIME}/{name}"] = secs
        row.update(self._row_stats(stats))
        return row

    @staticmethod
    def _row_stats(stats: dict[str, Any]) -> dict[str, Any]:
        return {
            f"{M.LOSS}/{key}": value
            for key, value in stats.items()
            if isinstance(value, (int, float)) and not isinstance(value, bool)
        }

    # ---- checkpoints ---------------------------------------------------------------------------
    def _driver_state(self) -> dict[str, Any]:
        return {
            "iteration": self.iteration,
            "next_episode": self.next_episode,
            "env_steps": self.env_steps,
            "current_policy": self.current_policy,
            "weight_version": self.weight_version,
            "policies": sorted(self.versions),
            "groups": self.group_info,
            "acted_other": self.acted_other,
            "stream": self.stream.state_dict(),
            "numpy_rng": np.random.get_state()[1].tolist(),
            "network_probe": self.backend.network_probe().tolist(),
            "torch_rng": torch.get_rng_state().tolist(),
        }

    def checkpoint(self) -> Path:
        """Write a checkpoint. An update still in flight (pipelined loop) is waited for but not
        published: the learner's state holds it, and the weights workers sample with until it is
        published are saved beside it, so a resumed run goes on exactly as an uninterrupted one."""
        pending = self._complete_pending()

        def write(tmp: Path) -> None:
            state = self._driver_state()
            if pending is not None:
                policy_id, stats, _ = pending
                state["pending_update"] = {"policy_id": policy_id, "stats": self._row_stats(stats)}
            (tmp / "driver.json").write_text(json.dumps(state))
            (tmp / "config.yaml").write_text(yaml.safe_dump(config_to_dict(self.cfg), sort_keys=False))
            self.backend.call_clustering("save", str(tmp / "bank"))
            (tmp / "learners").mkdir()
            for pid in sorted(self.versions):
                torch.save(self.backend.call_learner(pid, "state_dict"), tmp / "learners" / f"policy-{pid}.pt")
            if pending is not None:
                sampling = resolve_weights(self.handles[pending[0]])
                torch.save(sampling, tmp / "learners" / f"sampling-{pending[0]}.pt")

        return write_checkpoint(self.run_dir, self.iteration, write)

    def _restore(self, path: Path) -> None:
        state = json.loads((path / "driver.json").read_text())
        self.iteration = state["iteration"]
        self.next_episode = state["next_episode"]
        self.env_steps = state["env_steps"]
        self.current_policy = state["current_policy"]
        self.weight_version = state["weight_version"]
        self.group_info.update(state.get("groups", {}))
        self.acted_other = int(state.get("acted_other", 0))
        self.stream.load_state_dict(state["stream"])
        warning = probe_mismatch(state.get("network_probe"), self.backend.network_probe(), self.cfg)
        if warning:
            self.log(f"warning: {path}: {warning}")
        self.backend.call_clustering("load", str(path / "bank"))
        pending = state.get("pending_update")
        _drop_live_states(self.run_dir, keep=state["policies"])  # policies created after this checkpoint
        for pid in state["policies"]:
            self.backend.ensure_learner(pid)
            learner_state = torch.load(path / "learners" / f"policy-{pid}.pt", weights_only=False)
            self.backend.call_learner(pid, "load_state_dict", learner_state)
            self.learner_versions[pid], weights = self.backend.call_learner(pid, "weights")
            if pending is not None and pending["policy_id"] == pid:
                # the update in flight when the checkpoint was written: workers keep sampling with
                # the weights before it until the next iteration publishes it, as they would have
                sampling = torch.load(path / "learners" / f"sampling-{pid}.pt", weights_only=False)
                self._publish(pid, sampling)
                stats = {k.split("/", 1)[1]: v for k, v in pending["stats"].items()}
                self._pending_update = (pid, _Completed(stats, self.backend.publish(weights)))
            else:
                self._publish(pid, weights)
        self._prepare_next_learner()
        self.evaluation.rewind(self.iteration)
        self.log(f"resumed from {path} (iteration {self.iteration}, {self.env_steps} env steps)")

    # ---- the loop ------------------------------------------------------------------------------
    def _on_signal(self, signum: int, _frame: Any) -> None:
        self.log(f"received signal {signum}: checkpointing after this iteration")
        self._stop = True

    def run(self) -> dict[str, Any]:
        old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        resumed_at = None
        if self._resume_from is not None:  # rows of iterations after the checkpoint are redone: drop them
            resumed_at = int(json.loads((self._resume_from / "driver.json").read_text())["iteration"])
        rt = self.cfg.runtime
        writer = MetricsWriter(self.run_dir, resume_iteration=resumed_at, rotate_mb=rt.log_rotate_mb, keep=rt.log_keep)
        try:
            if self._resume_from is not None:
                self._restore(self._resume_from)
            else:
                self._new_policy(0)
            announce(self.run_dir, "driver")  # recorded once the loop runs
            progress = Progress(self.cfg.runtime.total_env_steps, self.cfg.runtime.log_every_s, self.env_steps)
            self._t_start, self._steps_at_start = time.monotonic(), self.env_steps
            row: dict[str, Any] = {}
            while self.env_steps < self.cfg.runtime.total_env_steps and not self._stop:
                row = self.step()
                if self.evaluation.due(self.iteration):
                    self.start_evaluation()
                row.update(self.evaluation.collect())
                self.backend.call_clustering("report", row)
                self.write_iteration(writer, row)
                progress.maybe_print(row)
                for hook in self.on_iteration:
                    hook()
                if self.iteration % self.cfg.runtime.checkpoint_every == 0:
                    self.checkpoint()
            if row and self.evaluation.enabled and not self._stop:  # a final pass, unless interrupted
                final = self.evaluation.collect(wait=True)  # a pass still running in the background
                if self.evaluation.last_iteration != self.iteration:
                    self.start_evaluation()
                    final.update(self.evaluation.collect(wait=True))
                if final:  # the iteration's row again, now with the pass's metrics (plots keep the last)
                    row.update(final)
                    self.backend.call_clustering("report", row)
                    writer.scalars(row)
            path = self.checkpoint()
            if row:
                progress.maybe_print(row, force=True)
            status = "interrupted" if self._stop else "finished"
            self.log(f"{status}: checkpoint {path}; resume with: covers-dist train --resume {self.run_dir}")
            return {"status": status, "row": row, "checkpoint": str(path), **self.backend.call_clustering("metrics")}
        finally:
            writer.close()
            for s, h in old.items():
                signal.signal(s, h)

    # ---- evaluation ------------------------------------------------------------------------------
    def start_evaluation(self) -> None:
        """Evaluate every (task, g) with the bank as it is now (serial: in place; Ray: in the background)."""
        weights_map = self.newest_weights()
        confusion = self.backend.call_clustering("metrics").get("confusion", {})
        info = {
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "source": "training",
            "groups": {t: dict(v) for t, v in self.group_info.items()},
        }
        episodes_done = self.next_episode
        with torch.random.fork_rng(devices=[]):  # building the evaluation worker's model draws random numbers
            executors = self.backend.eval_executors()

        def choose(obs: dict[str, np.ndarray], groups: list[int]) -> dict[str, Any]:
            # only the policies of this pass's weights: on Ray, training goes on meanwhile and the bank
            # may hold a policy whose weights are not published yet
            return self.backend.call_clustering("what_if", obs, groups, sorted(weights_map))

        def make_pass() -> dict[str, Any]:
            return evaluation_pass(
                self.cfg, executors, self.stream, episodes_done, choose, confusion, weights_map, info, log=self.log
            )

        with torch.random.fork_rng(devices=[]):  # a serial pass runs here: training's torch RNG stays as it was
            self.evaluation.start(self.iteration, make_pass)

    def write_iteration(self, writer: Any, row: dict[str, Any]) -> None:
        """Log the iteration just stepped: its metrics row and its episodes (a ``MetricsWriter``)."""
        writer.scalars(row)
        writer.episodes(self._last_episode_rows())

    def _last_episode_rows(self) -> list[dict[str, Any]]:
        steps = self.env_steps - sum(s["length"] for s in self._last_rows)
        rows = []
        for s in self._last_rows:
            steps += s["length"]
            rows.append({**s, M.ENV_STEPS: steps, M.ITERATION: self.iteration})
        return rows

    def close(self) -> None:
        self.backend.shutdown()


@dataclass(frozen=True)
class _Completed:
    """An update that has finished on its learner but whose weights are not published yet."""

    stats: dict[str, Any]
    handle: Any


def _drop_live_states(run_dir: Path, keep: list[int] | None = None) -> None:
    """Remove the learners' live states (:mod:`.learner`) of policies not in ``keep`` (all if None)."""
    live = run_dir / LIVE_DIR
    if not live.is_dir():
        return
    kept = {live_state_path(run_dir, pid).name for pid in keep or []}
    for f in live.iterdir():
        if f.name not in kept:
            f.unlink(missing_ok=True)


def _field(item: Any, name: str) -> Any:
    return item[name] if isinstance(item, dict) else getattr(item, name)


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
        cfg_path = Path(resume_dir) / "config.yaml"
        if not cfg_path.is_file():
            raise FileNotFoundError(f"{resume_dir} is not a run directory (no config.yaml)")
        cfg = load_run_config(cfg_path)
    assert cfg is not None
    run_dir = Path(cfg.runtime.run_dir)
    if resume_dir is None and (run_dir / "checkpoints").is_dir() and any((run_dir / "checkpoints").iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"{run_dir} already holds a run: continue it with --resume {run_dir}, "
                "choose another --run-dir, or pass --overwrite to start over"
            )
        for name in ("checkpoints", CLUSTERING_LIVE_DIR, LIVE_DIR, "tb"):
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

            init_ray(cfg.runtime.num_cpus, cfg.runtime.ray_address, cfg.runtime.num_gpus or None)
            started = True
            graceful()  # ray.init replaced it with one that exits at once
        trainer = Trainer(cfg, resume=resume_dir is not None, log=log)
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
        if started:
            shutdown_ray()
        for s, h in original.items():
            signal.signal(s, h)
