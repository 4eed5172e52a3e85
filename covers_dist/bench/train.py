"""``covers-dist bench train``: end-to-end env steps/s of the COVERS loop vs RLlib's PPO.

In one run, on one machine: the whole loop (sample -> assign -> update -> publish) on the given
config with 1 and with 2 rollout workers, then RLlib's PPO (new API stack) on the same base task,
same image size, with a CNN of comparable size, sampling with the same number of env runners and
envs per runner. Also reports the sampling phase's speed-up from 1 to 2 workers and the peak
resident memory of all processes of the run (driver + every Ray process), sampled every 0.2 s.

A third setting runs the loop with the CNN twin (``covers-cnn``), whose compute per sample is
close to RLlib's CNN, so that the runtime is compared with the network cost held comparable.

Targets (reported, not asserted): end-to-end steps/s >= 2x RLlib's; sampling with 2 workers
>= 1.7x with 1; peak memory <= 4 GiB.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from ..config import load_config

GIB = 1024**3


class PeakMemory:
    """Peak summed RSS of this process and every process whose command line mentions ``marker``."""

    def __init__(self, marker: str | None) -> None:
        self.marker = marker
        self.peak = 0
        self.processes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _rss(self) -> int:
        total, count = 0, 0
        page = os.sysconf("SC_PAGE_SIZE")
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                mine = int(entry.name) == os.getpid()
                if not mine and self.marker:
                    cmd = (entry / "cmdline").read_bytes()
                    mine = self.marker.encode() in cmd
                if mine:
                    total += int((entry / "statm").read_text().split()[1]) * page
                    count += 1
            except (OSError, ValueError):
                continue
        self.processes = max(self.processes, count)
        return total

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            self._stop.wait(0.2)

    def __enter__(self) -> "PeakMemory":
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="end-to-end steps/s of the loop (1 and 2 workers) vs RLlib PPO, peak memory")
    p.add_argument("--config", default="configs/quickstart.yaml", help="config (default: configs/quickstart.yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--iterations", type=int, default=6, help="measured iterations per setting (default: 6)")
    p.add_argument("--warmup", type=int, default=1, help="unmeasured iterations first (default: 1)")
    p.add_argument("--skip-rllib", action="store_true", help="measure covers-dist only")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def _covers(cfg_path: str, overrides: list[str], workers: int, iters: int, warmup: int) -> dict[str, float]:
    """The COVERS loop on a local Ray instance; memory covers every process of that instance."""
    import ray

    from ..runtime.driver import Trainer
    from ..runtime.ray_setup import init_ray, shutdown_ray

    run_dir = tempfile.mkdtemp(prefix="covers-bench-")
    cfg = load_config(cfg_path, [*overrides, f"runtime.num_workers={workers}", f"runtime.run_dir={run_dir}"])
    init_ray(cfg.runtime.num_cpus)
    session_dir = ray._private.worker.global_worker.node.get_session_dir_path()
    trainer = Trainer(cfg, log=lambda *_: None)
    try:
        with PeakMemory(str(Path(session_dir).parent)) as mem:
            trainer._new_policy(0)
            for _ in range(warmup):
                trainer.step()
            steps0, t0, sample_s = trainer.env_steps, time.perf_counter(), 0.0
            for _ in range(iters):
                trainer.step()
                sample_s += trainer.phase_time["sample"]
            elapsed = time.perf_counter() - t0
            steps = trainer.env_steps - steps0
    finally:
        trainer.close()
        shutdown_ray()
    return {
        "env_steps_per_s": steps / elapsed,
        "sample_steps_per_s": steps / sample_s,
        "peak_rss_gib": mem.peak / GIB,
        "processes": mem.processes,
        "env_steps": steps,
        "update_s_per_iter": trainer.phase_time.get("update", 0.0),
    }


def _rllib(cfg_path: str, overrides: list[str], iters: int, warmup: int) -> dict[str, float]:
    from ..runtime.ray_setup import init_ray, shutdown_ray
    from .rllib_peer import build_rllib_ppo

    cfg = load_config(cfg_path, overrides)
    init_ray(cfg.runtime.num_cpus)
    algo = build_rllib_ppo(cfg)
    try:
        for _ in range(warmup):
            algo.train()
        t0 = time.perf_counter()
        steps = 0
        for _ in range(iters):
            result = algo.train()
            steps += int(result["env_runners"]["num_env_steps_sampled"])
        elapsed = time.perf_counter() - t0
    finally:
        algo.stop()
        shutdown_ray()
    return {"env_steps_per_s": steps / elapsed, "env_steps": steps}


def run(args: argparse.Namespace) -> int:
    if args.iterations < 1 or args.warmup < 0:
        raise SystemExit("covers-dist bench train: --iterations must be >= 1 and --warmup >= 0")
    cfg = load_config(args.config, args.overrides)
    out: dict[str, Any] = {"config": args.config, "task": cfg.env.tasks[0], "image_size": cfg.env.image_size}
    cnn = ["runtime.method=covers-cnn", "network.kind=cnn"]
    for name, workers, extra in (("covers_1w", 1, []), ("covers_2w", 2, []), ("covers_cnn_2w", 2, cnn)):
        r = _covers(args.config, [*args.overrides, *extra], workers, args.iterations, args.warmup)
        out[name] = {k: round(v, 3) for k, v in r.items()}
        if not args.json:
            print(f"{name}: {r['env_steps_per_s']:.0f} env steps/s end to end, "
                  f"{r['sample_steps_per_s']:.0f} in sampling, peak RSS {r['peak_rss_gib']:.2f} GiB "
                  f"over {r['processes']} processes", flush=True)
    out["sampling_speedup_2w_vs_1w"] = round(
        out["covers_2w"]["sample_steps_per_s"] / out["covers_1w"]["sample_steps_per_s"], 3
    )
    out["peak_rss_gib"] = max(out["covers_1w"]["peak_rss_gib"], out["covers_2w"]["peak_rss_gib"])
    if not args.skip_rllib:
        rl = _rllib(args.config, args.overrides, args.iterations, args.warmup)
        out["rllib_ppo"] = {k: round(v, 3) for k, v in rl.items()}
        out["covers_to_rllib"] = round(out["covers_2w"]["env_steps_per_s"] / rl["env_steps_per_s"], 3)
        out["covers_cnn_to_rllib"] = round(out["covers_cnn_2w"]["env_steps_per_s"] / rl["env_steps_per_s"], 3)
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))
    return 0
