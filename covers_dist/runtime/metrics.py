"""Run metrics: names, JSONL + TensorBoard writers, and the console progress line.

Files in the run directory:

* ``metrics.jsonl``: one JSON object per update step (the keys below, plus PPO stats);
* ``episodes.jsonl``: one JSON object per episode (index, task, g, true group, policy id, return,
  success, length, env steps so far) - what ``covers-dist plot`` draws the clustering from;
* ``tb/``: TensorBoard event files with the same scalars.

Disk use stays bounded (:mod:`covers_dist.runtime.logfiles`): a JSONL log that reaches
``rotate_mb`` becomes a gzip segment (``episodes.jsonl.<seq>.gz``), of which the newest ``keep``
are kept; an event file that reaches ``rotate_mb`` is closed and a new one opened, and the oldest
closed event files are deleted while there are more than ``keep`` of them holding more than
``keep * rotate_mb``. Read the logs with :func:`read_jsonl_segments`. A resumed run passes the
iteration of its checkpoint: the rows after it (which the run is about to redo) leave
metrics.jsonl, episodes.jsonl and eval.jsonl, and TensorBoard hides the scalars after it
(``purge_step``).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

from ..config import RuntimeConfig
from .logfiles import JsonlLog, read_jsonl_file, read_jsonl_segments, segment_paths, truncate_after_iteration

__all__ = ["MetricsWriter", "Progress", "M", "read_jsonl_segments", "METRICS_LOG", "EPISODES_LOG"]

METRICS_LOG = "metrics.jsonl"
EPISODES_LOG = "episodes.jsonl"
_EVENTS = "events.out.tfevents.*"


class M:
    """Metric names (one place, used by the driver, the plots and the HTTP service)."""

    ITERATION = "iteration"
    EPISODES = "episodes"
    ENV_STEPS = "env_steps"
    STEPS_PER_S = "env_steps_per_s"
    POLICY = "policy_id"
    NUM_POLICIES = "num_policies"
    ARI = "ari"
    NEW_POLICY = "new_policy"
    #: fraction of the episodes so far acted by a policy other than the one they were assigned to
    WRONG_POLICY = "wrong_policy_fraction"
    DISTANCE_MIN = "assign/min_distance"
    SUCCESS = "success"  # success/<task>
    RETURN = "return"  # return/<task>
    TIME = "time"  # time/<phase>
    LOSS = "ppo"  # ppo/<stat>
    #: the colour of the batch's training noise (rows of runs with ppo.noise_beta > 0)
    NOISE_BETA = "noise_beta"


class MetricsWriter:
    """Appends metrics to JSONL files and TensorBoard; resumable (append mode).

    ``rotate_mb``: size (MiB) of a live log or event file that triggers a rotation (None: never);
    ``keep``: rotated JSONL segments kept per log, and closed event files kept (more while they
    hold no more than ``keep * rotate_mb``); ``resume_iteration``: the iteration of the checkpoint
    a resumed run starts from (the rows after it are removed first).
    """

    def __init__(
        self,
        run_dir: str | Path,
        tensorboard: bool = True,
        resume_iteration: int | None = None,
        rotate_mb: float | None = RuntimeConfig.log_rotate_mb,
        keep: int = RuntimeConfig.log_keep,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.rotate_bytes = None if rotate_mb is None else max(int(rotate_mb * 2**20), 1)
        self.keep = keep
        purge_step = None
        if resume_iteration is not None:
            purge_step = self._truncate(resume_iteration)
        self._metrics = JsonlLog(self.run_dir / METRICS_LOG, self.rotate_bytes, keep)
        self._episodes = JsonlLog(self.run_dir / EPISODES_LOG, self.rotate_bytes, keep)
        self.tb_dir = self.run_dir / "tb"
        self._tb = self._tb_file = None
        if tensorboard:
            self._open_tb(purge_step)

    def _truncate(self, iteration: int) -> int:
        """Drop the rows after ``iteration`` from the logs; returns TensorBoard's purge step (the
        first env step after the last row kept)."""
        from ..evaluation.runner import EVAL_LOG

        last_steps = None
        live = self.run_dir / METRICS_LOG
        files = ([live] if live.is_file() else []) + segment_paths(self.run_dir, METRICS_LOG)[::-1]
        for path in files:  # newest first: the last row at or before ``iteration``
            rows = [r for r in read_jsonl_file(path, strict=False) if r.get(M.ITERATION, math.inf) <= iteration]
            if rows:
                last_steps = int(rows[-1].get(M.ENV_STEPS, 0))
                break
        for name in (METRICS_LOG, EPISODES_LOG, EVAL_LOG):
            truncate_after_iteration(self.run_dir, name, iteration)
        return 0 if last_steps is None else last_steps + 1

    def _open_tb(self, purge_step: int | None = None) -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:  # pragma: no cover - tensorboard is a dependency
            return
        before = set(self.tb_dir.glob(_EVENTS))
        self._tb = SummaryWriter(str(self.tb_dir), purge_step=purge_step)
        new = sorted(set(self.tb_dir.glob(_EVENTS)) - before)
        self._tb_file = new[0] if len(new) == 1 else None
        self._prune_tb()

    def _prune_tb(self) -> None:
        """Delete the oldest closed event files while there are more than ``keep`` of them and they
        hold more than ``keep * rotate_mb`` (small files left by restarts are kept)."""
        if self.rotate_bytes is None:
            return
        closed = [p for p in self.tb_dir.glob(_EVENTS) if p != self._tb_file]
        closed.sort(key=lambda p: (p.stat().st_mtime, p.name))
        sizes = [p.stat().st_size for p in closed]
        while len(closed) > self.keep and sum(sizes) > self.keep * self.rotate_bytes:
            closed.pop(0).unlink()
            sizes.pop(0)

    def episodes(self, rows: list[dict[str, Any]]) -> None:
        self._episodes.write(rows)

    def scalars(self, row: dict[str, Any]) -> None:
        self._metrics.write([row])
        if self._tb is not None:
            step = int(row.get(M.ENV_STEPS, 0))
            for key, value in row.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                    self._tb.add_scalar(key, value, step)
            self._tb.flush()
            if self.rotate_bytes is not None and self._tb_file is not None:
                if self._tb_file.stat().st_size >= self.rotate_bytes:
                    self._tb.close()
                    self._open_tb()

    def close(self) -> None:
        self._metrics.close()
        self._episodes.close()
        if self._tb is not None:
            self._tb.close()


class Progress:
    """Periodic console progress lines with rates and ETA."""

    def __init__(self, total_env_steps: int, every_s: float, start_steps: int = 0, deadline: float | None = None) -> None:
        self.total = total_env_steps
        self.every_s = every_s
        self.t0 = time.monotonic()
        self.deadline = deadline  # time.monotonic() at which a time limit ends the run (ETA: whichever comes first)
        self.start_steps = start_steps
        self._last = -math.inf

    def maybe_print(self, row: dict[str, Any], force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last < self.every_s:
            return
        self._last = now
        steps = row.get(M.ENV_STEPS, 0)
        rate = (steps - self.start_steps) / max(now - self.t0, 1e-9)
        eta = (self.total - steps) / rate if rate > 0 else math.inf
        if self.deadline is not None:
            eta = min(eta, max(self.deadline - now, 0.0))
        succ = " ".join(
            f"{k.split('/', 1)[1]}={v:.2f}" for k, v in sorted(row.items()) if k.startswith(M.SUCCESS + "/")
        )
        print(
            f"[{_hms(now - self.t0)}] episodes={row.get(M.EPISODES, 0)} steps={steps}/{self.total} "
            f"({100.0 * steps / self.total:.0f}%) {rate:,.0f} steps/s | policy={row.get(M.POLICY)} "
            f"policies={row.get(M.NUM_POLICIES)} ARI={row.get(M.ARI, float('nan')):.3f} | success {succ} | "
            f"ETA {_hms(eta)}",
            flush=True,
        )


def _hms(s: float) -> str:
    if not math.isfinite(s):
        return "--:--"
    s = int(s)
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}"
