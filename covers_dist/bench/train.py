"""``covers-dist bench train``: end-to-end env steps/s of the COVERS loop vs RLlib's PPO.

In one run, on one machine, each setting on a fresh local Ray instance:

* ``covers_1w`` / ``covers_2w``: the whole loop on the given config with 1 and 2 rollout workers
  (pipelined, the default); ``covers_2w_sequential``: the same with ``runtime.pipeline=false``;
  ``covers_2w_2threads``: the same with the learner on two torch threads (``runtime.learner_threads``;
  auto gives a learner that shares the workers' cores one); ``covers_2w_s2d4``: the same with the
  coarser stem (``network.space_to_depth: 4``; ``s2d4_vs_config`` is its speed over the config's);
  ``covers_2w_shared``: the same with every policy's learner in one process
  (``runtime.learners_per_process``); ``covers_cnn_2w``: the loop with the CNN twin (COVERS-CNN:
  its features are not invariant, so the bank makes a policy, and starts a learner, for each new
  copy of the table); ``covers_cnn_2w_shared``: the same with every learner in one process;
  ``cnn_2w``: the loop with one CNN-twin policy for the whole stream (the CNN baseline: one
  network, as RLlib);
* ``rllib_ppo``: RLlib's PPO (new API stack) on the same base task and image size with RLlib's
  default CNN on the image alone; ``rllib_same_net_cnn`` / ``rllib_same_net_equivariant``: RLlib's
  PPO training covers-dist's own network (CNN twin / equivariant) through the RLModule adapter
  (:mod:`covers_dist.integrations.rllib`), on image + proprio: equal compute per sample.

RLlib samples with the same number of env runners and envs per runner, one train batch is one
covers-dist iteration, with the same epochs, minibatch and learning rate. Also reported: the
sampling phase's speed-up from 1 to 2 workers, the peak resident memory of all processes of a
run (driver + every process of its Ray instance, actors included, sampled every 0.2 s) and of its
learner processes, the seconds per iteration of each phase of the loop, the policies the bank
created inside the measured window with the seconds their starts took (a new policy's learner and
first weights, inside the ``assign`` phase), the learner processes the run started, and the
ratios the targets name (``shared_learner_memory`` / ``_speed``: one learner process for every
policy against one each, equivariant; ``cnn_shared_learner_*``: the same for COVERS-CNN).

Targets (reported, not asserted): equivariant loop >= 1.0x RLlib's default-CNN PPO; CNN-twin
loop >= 2x RLlib on the same network; 2 workers > 1 worker end to end; peak memory <= 4 GiB.
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
    """Peak summed RSS of this process, the processes whose command line mentions ``marker`` (a Ray
    instance's session directory: its raylet and GCS, also when another process started them) and
    every process descended from those (the actors), sampled every 0.2 s; also the peak summed RSS
    of the learner processes among them (command line ``ray::_LearnerHost...``). Pages shared
    between processes (the Python and torch libraries) count once per process."""

    LEARNER = b"_LearnerHost"

    def __init__(self, marker: str | None = None) -> None:
        self.marker = marker.encode() if marker else None
        self.peak = 0
        self.learner_peak = 0
        self.processes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _tree(self) -> dict[int, bytes]:
        """pid -> command line of every process counted."""
        children: dict[int, list[int]] = {}
        cmdlines: dict[int, bytes] = {}
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                cmdlines[int(entry.name)] = (entry / "cmdline").read_bytes()
            except (OSError, ValueError, IndexError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
        todo = [os.getpid(), *(p for p, c in cmdlines.items() if self.marker and self.marker in c)]
        out: dict[int, bytes] = {}
        while todo:
            pid = todo.pop()
            if pid not in out:
                out[pid] = cmdlines.get(pid, b"")
                todo += children.get(pid, [])
        return out

    def _sample(self) -> None:
        page = os.sysconf("SC_PAGE_SIZE")
        total = learners = count = 0
        for pid, cmdline in self._tree().items():
            try:
                rss = int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * page
            except (OSError, ValueError, IndexError):
                continue
            total += rss
            learners += rss if self.LEARNER in cmdline else 0
            count += 1
        self.peak = max(self.peak, total)
        self.learner_peak = max(self.learner_peak, learners)
        self.processes = max(self.processes, count)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
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
    p.add_argument(
        "--settings", default=None,
        help="comma-separated subset of: " + ", ".join([*COVERS_SETTINGS, *RLLIB_SETTINGS]) + " (default: all)",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def _covers(
    cfg_path: str, overrides: list[str], workers: int, iters: int, warmup: int, address: str | None = None
) -> dict[str, float]:
    """The COVERS loop on a local Ray instance (or the cluster at ``address``); memory covers every
    process of that instance; ``phase_<name>_s`` are mean seconds per iteration of each phase."""
    import ray

    from ..runtime.driver import Trainer
    from ..runtime.ray_setup import init_ray, shutdown_ray

    run_dir = tempfile.mkdtemp(prefix="covers-bench-")
    cfg = load_config(cfg_path, [*overrides, f"runtime.num_workers={workers}", f"runtime.run_dir={run_dir}"])
    init_ray(cfg.runtime.num_cpus, address)
    session_dir = ray._private.worker.global_worker.node.get_session_dir_path()
    trainer = Trainer(cfg, log=lambda *_: None)
    starts: list[float] = []  # seconds of each policy start (learner + first weights) in the window
    start_policy = trainer.start_policy

    def timed_start(policy_id: int) -> None:
        t = time.perf_counter()
        start_policy(policy_id)
        starts.append(time.perf_counter() - t)

    try:
        with PeakMemory(str(Path(session_dir).parent)) as mem:
            trainer.start_policy(0)
            for _ in range(warmup):
                trainer.step()
            trainer.drain()  # the window holds exactly its own iterations' sampling and updates
            trainer.start_policy = timed_start  # type: ignore[method-assign]  # the bank's new policies
            steps0, t0, phases = trainer.env_steps, time.perf_counter(), {}
            for _ in range(iters):
                trainer.phase_time.clear()
                trainer.step()
                for name, secs in trainer.phase_time.items():
                    phases[name] = phases.get(name, 0.0) + secs
            trainer.drain()
            elapsed = time.perf_counter() - t0
            sample_s = phases["sample"]
            steps = trainer.env_steps - steps0
            policies = len(trainer.weights.versions)
            learner_processes = trainer.backend.learner_processes()
    finally:
        trainer.close()
        shutdown_ray()
    return {
        "env_steps_per_s": steps / elapsed,
        "sample_steps_per_s": steps / sample_s,
        "peak_rss_gib": mem.peak / GIB,
        "learner_peak_rss_gib": mem.learner_peak / GIB,
        "processes": mem.processes,
        "env_steps": steps,
        # the update's own time beside (pipelined) or after (sequential) the sampling
        "update_s_per_iter": (phases.get("update_submit", 0.0) + phases.get("update_wait", 0.0)) / iters,
        # policies the bank created inside the window and the seconds their starts took (part of `assign`)
        "policies_created": len(starts),
        "policy_start_s_per_iter": sum(starts) / iters,
        "policies": policies,
        "learner_processes": learner_processes,  # started in the whole run (the one started ahead included)
        **{f"phase_{name}_s": secs / iters for name, secs in phases.items()},
    }


def _rllib(cfg_path: str, overrides: list[str], iters: int, warmup: int, network: str = "default") -> dict[str, float]:
    from ..runtime.ray_setup import init_ray, shutdown_ray
    from .rllib_peer import build_rllib_ppo

    cfg = load_config(cfg_path, overrides)
    init_ray(cfg.runtime.num_cpus)
    algo = build_rllib_ppo(cfg, network)
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


COVERS_SETTINGS = {  # name: (rollout workers, overrides)
    "covers_1w": (1, []),
    "covers_2w": (2, []),
    "covers_2w_sequential": (2, ["runtime.pipeline=false"]),
    # the learner on two torch threads beside the workers (auto gives a learner without cores of its
    # own one): a core idles while the driver waits for an update longer than its sampling (an fp32
    # update on a CPU without native bf16), docs/research/runtime.md run F
    "covers_2w_2threads": (2, ["runtime.learner_threads=2"]),
    # the coarser stem (4x4 pixel blocks folded into channels: ~2.4x the equivariant update on an
    # AVX2 CPU, bench learner): what the loop gains end to end where the update is the longer phase
    "covers_2w_s2d4": (2, ["network.space_to_depth=4"]),
    # every policy's learner in one process (runtime.learners_per_process): a new policy costs a
    # network build in that process, not a process start, and no idle process waits ahead
    "covers_2w_shared": (2, ["runtime.learners_per_process=64"]),
    "covers_cnn_2w": (2, ["runtime.method=covers-cnn", "network.kind=cnn"]),
    # the same with every policy's learner in one process (runtime.learners_per_process): a new
    # policy costs a network build in that process, not a process start
    "covers_cnn_2w_shared": (2, ["runtime.method=covers-cnn", "network.kind=cnn", "runtime.learners_per_process=64"]),
    # one CNN-twin policy for the whole stream, as RLlib trains one network: the bank never creates
    # another, so no learner starts inside the window (COVERS-CNN makes one per new copy of the table)
    "cnn_2w": (2, ["runtime.method=cnn", "network.kind=cnn"]),
}
RLLIB_SETTINGS = {  # name: (network, overrides)
    "rllib_ppo": ("default", []),
    "rllib_same_net_cnn": ("covers", ["runtime.method=covers-cnn", "network.kind=cnn"]),
    "rllib_same_net_equivariant": ("covers", []),
}


#: shared learner process against one per policy: peak memory and end-to-end speed ratios
SHARED_PAIRS = {
    "shared_learner": ("covers_2w_shared", "covers_2w"),
    "cnn_shared_learner": ("covers_cnn_2w_shared", "covers_cnn_2w"),
}


def _ratio(out: dict[str, Any], a: str, b: str) -> float | None:
    if a in out and b in out:
        return round(out[a]["env_steps_per_s"] / out[b]["env_steps_per_s"], 3)
    return None


def run(args: argparse.Namespace) -> int:
    if args.iterations < 1 or args.warmup < 0:
        raise SystemExit("covers-dist bench train: --iterations must be >= 1 and --warmup >= 0")
    known = [*COVERS_SETTINGS, *RLLIB_SETTINGS]
    chosen = [s.strip() for s in args.settings.split(",")] if args.settings else known
    unknown = [s for s in chosen if s not in known]
    if unknown:
        raise SystemExit(f"covers-dist bench train: unknown setting(s) {unknown}; choose from {known}")
    if args.skip_rllib:
        chosen = [s for s in chosen if s not in RLLIB_SETTINGS]
    from ..ppo.learner import native_bf16_cpu

    cfg = load_config(args.config, args.overrides)
    out: dict[str, Any] = {
        "config": args.config, "task": cfg.env.tasks[0], "image_size": cfg.env.image_size,
        "space_to_depth": cfg.network.space_to_depth, "iterations": args.iterations,
        "native_bf16_cpu": native_bf16_cpu(),
    }  # fmt: skip
    for name in chosen:
        if name in COVERS_SETTINGS:
            workers, extra = COVERS_SETTINGS[name]
            r = _covers(args.config, [*args.overrides, *extra], workers, args.iterations, args.warmup)
            if not args.json:
                print(f"{name}: {r['env_steps_per_s']:.0f} env steps/s end to end, "
                      f"{r['sample_steps_per_s']:.0f} in sampling, peak RSS {r['peak_rss_gib']:.2f} GiB "
                      f"over {r['processes']} processes ({r['learner_peak_rss_gib']:.2f} GiB in learners); "
                      f"{r['policies_created']} policies created in the window ({r['policy_start_s_per_iter']:.2f} s "
                      f"per iteration starting them), {r['learner_processes']} learner processes", flush=True)
        else:
            network, extra = RLLIB_SETTINGS[name]
            r = _rllib(args.config, [*args.overrides, *extra], args.iterations, args.warmup, network)
            if not args.json:
                print(f"{name}: {r['env_steps_per_s']:.0f} env steps/s", flush=True)
        out[name] = {k: round(v, 3) for k, v in r.items()}
    if "covers_1w" in out and "covers_2w" in out:
        out["sampling_speedup_2w_vs_1w"] = round(
            out["covers_2w"]["sample_steps_per_s"] / out["covers_1w"]["sample_steps_per_s"], 3
        )
    rss = [v["peak_rss_gib"] for k, v in out.items() if isinstance(v, dict) and "peak_rss_gib" in v]
    if rss:
        out["peak_rss_gib"] = max(rss)
    for key, (a, b) in SHARED_PAIRS.items():  # one learner process against one per policy
        if a in out and b in out:
            out[f"{key}_memory"] = round(out[a]["peak_rss_gib"] / out[b]["peak_rss_gib"], 3)
            out[f"{key}_speed"] = _ratio(out, a, b)
    ratios = {
        "end_to_end_2w_vs_1w": ("covers_2w", "covers_1w"),
        "pipeline_vs_sequential": ("covers_2w", "covers_2w_sequential"),
        "learner_2threads_vs_auto": ("covers_2w_2threads", "covers_2w"),
        "s2d4_vs_config": ("covers_2w_s2d4", "covers_2w"),
        "covers_to_rllib": ("covers_2w", "rllib_ppo"),
        "covers_cnn_to_rllib": ("covers_cnn_2w", "rllib_ppo"),
        "covers_to_rllib_same_net": ("covers_2w", "rllib_same_net_equivariant"),
        "covers_cnn_to_rllib_same_net": ("covers_cnn_2w", "rllib_same_net_cnn"),
        "cnn_to_rllib_same_net": ("cnn_2w", "rllib_same_net_cnn"),
    }
    for key, (a, b) in ratios.items():
        value = _ratio(out, a, b)
        if value is not None:
            out[key] = value
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))
    return 0
