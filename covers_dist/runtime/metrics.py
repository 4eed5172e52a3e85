"""Run metrics: names, JSONL + TensorBoard writers, and the console progress line.

Files in the run directory:

* ``metrics.jsonl``: one JSON object per update step (the keys below, plus PPO stats);
* ``episodes.jsonl``: one JSON object per episode (index, task, g, true group, policy id, return,
  success, length, env steps so far) - what ``covers-dist plot`` draws the clustering from;
* ``tb/``: TensorBoard event files with the same scalars.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

__all__ = ["MetricsWriter", "Progress", "M"]


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


class MetricsWriter:
    """Appends metrics to JSONL files and TensorBoard; resumable (append mode)."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._metrics = open(self.run_dir / "metrics.jsonl", "a", buffering=1)
        self._episodes = open(self.run_dir / "episodes.jsonl", "a", buffering=1)
        self._tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb = SummaryWriter(str(self.run_dir / "tb"))
            except ImportError:  # pragma: no cover - tensorboard is a dependency
                self._tb = None

    def episodes(self, rows: list[dict[str, Any]]) -> None:
        for row in rows:
            self._episodes.write(json.dumps(row) + "\n")

    def scalars(self, row: dict[str, Any]) -> None:
        self._metrics.write(json.dumps(row, default=float) + "\n")
        if self._tb is not None:
            step = int(row.get(M.ENV_STEPS, 0))
            for key, value in row.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                    self._tb.add_scalar(key, value, step)

    def close(self) -> None:
        self._metrics.close()
        self._episodes.close()
        if self._tb is not None:
            self._tb.close()


class Progress:
    """Periodic console progress lines with rates and ETA."""

    def __init__(self, total_env_steps: int, every_s: float, start_steps: int = 0) -> None:
        self.total = total_env_steps
        self.every_s = every_s
        self.t0 = time.monotonic()
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
