"""``covers-dist bench chaos``: kill parts of a training run at random; it must end where a clean run ends.

Two runs of the same config and seed, one after the other:

1. **clean**: the run in this process with every component in it (``runtime.serial``; the Ray
   run gives the same assignments and bit-identical weights, see tests/test_pipeline.py);
2. **chaos**: ``covers-dist train`` as a child process on its own loopback-only Ray instance,
   with the HTTP service on, while every ``--interval`` seconds (uniform in MIN..MAX, from a
   seeded schedule) one live component is killed: a rollout worker, a learner, the clustering
   actor or the HTTP service by SIGKILL (a crash), the driver by SIGTERM (``driver``: it
   checkpoints and exits), or the driver's whole process group by SIGKILL (``driver-kill``: the
   driver and the Ray instance it started die at once, as when its machine or container goes;
   what that incarnation started and left behind is then killed by PID), each followed by
   ``covers-dist train --resume``. Victims are found in the run's ``processes/`` records.

Compared at the end, from the two runs' final checkpoints and logs: the assignment of every
batch (policy and decision), every episode index logged exactly once, every policy's final
weights (exactly equal, or the largest difference; a NaN anywhere is a difference), and the whole
state (:func:`final_state`): every learner's optimizer moments, schedule and version, the driver's
counters and stream position, the bank's buffers, history and counters, and every row of metrics.jsonl
and eval.jsonl, with only wall-clock fields (:data:`VOLATILE`) left out. Any difference fails the
verdict, named by its path.
``--node-loss workers|learners`` runs a different fault instead: a local 2-node cluster
(:mod:`covers_dist.runtime.local_cluster`) where the node holding the rollout workers (or the
learners) is removed mid-run; the run continues on the surviving node. With ``--isolated-disk``
that node shares no disk with the driver (its own mount namespace, an empty tmpfs over the run
directories; root only) and the run's state goes through ``runtime.storage`` (a URI every node
reaches), as on a cluster without a shared filesystem. Target: identical assignments and
weights after >= 20 kills.

The verdict (exit status 0, ``"verdict": true``) needs the faults as well as the equality: every
kind named in ``--kinds`` killed at least once (with ``--max-kills N``, the last kills go to the
kinds not killed yet, so N >= the number of kinds gets each of them), and with ``--node-loss`` the
node actually removed. Otherwise the command exits 1 and names each reason (``"failures"``).
Arguments that cannot give the faults (``--max-kills`` below the number of kinds, ``--lose-after``
at or past the run's last iteration) are refused before anything runs (exit status 2).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, NoReturn

from ..config import Config, load_config, load_run_config
from ..runtime.processes import list_processes, running
from ..runtime.run_storage import storage_location
from ..storage import is_uri, storage_child

KINDS = ("worker", "learner", "clustering", "api", "driver", "driver-kill")
#: The process role (``processes/`` records) each kind of kill picks its victim from.
ROLE = {"driver-kill": "driver"}
TARGET_KILLS = 20
PROG = "covers-dist bench chaos"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("chaos", help="kill workers, learners, the clustering actor, the HTTP service and the driver "
                       "at random; compare with a clean run")  # fmt: skip
    p.add_argument("--config", default="configs/smoke.yaml", help="config (default: configs/smoke.yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--interval", default="2,5", help="seconds between kills, MIN,MAX (default: 2,5)")
    p.add_argument("--kinds", default=",".join(KINDS), help=f"what may be killed (default: {','.join(KINDS)})")
    p.add_argument("--seed", type=int, default=0, help="seed of the kill schedule (default: 0)")
    p.add_argument("--max-kills", type=int, default=0,
                   help="stop killing after this many, at least one per kind (default: 0, no limit)")  # fmt: skip
    p.add_argument(
        "--node-loss", choices=("workers", "learners"),
        help="instead of kills: remove the node holding the rollout workers (or the learners) of a 2-node cluster",
    )  # fmt: skip
    p.add_argument(
        "--isolated-disk", action="store_true",
        help="--node-loss: the second node shares no disk with the driver (its own mount namespace with an empty "
             "tmpfs over the run directories; root only); needs --set runtime.storage=URI that every node reaches",
    )  # fmt: skip
    p.add_argument("--lose-after", type=int, default=3,
                   help="--node-loss: iterations before the node goes, 1 to the run's iterations - 1 "
                        "(default: 3)")  # fmt: skip
    p.add_argument("--out", help="keep both run directories under OUT (default: a temp dir, removed)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


# ---- the clean run and the comparison -------------------------------------------------------------
def clean_run(cfg: Config) -> float:
    """The run in this process (serial); its wall-clock seconds."""
    from ..runtime.driver import Trainer

    t0 = time.monotonic()
    trainer = Trainer(cfg, log=lambda *_: None)
    try:
        trainer.run()
    finally:
        trainer.close()
    return time.monotonic() - t0


#: Fields that hold wall-clock readings (seconds, rates, timestamps): the only ones a fault may change.
VOLATILE = frozenset({"wall_time", "wall_time_ms", "time_unix", "time_s", "created_at_time"})


def _volatile(key: str) -> bool:
    return key in VOLATILE or key.startswith("time/") or key.endswith("_per_s") or key.endswith("update_time_s")


def stable(obj: Any) -> Any:
    """``obj`` (JSON-like) without its wall-clock fields (:data:`VOLATILE`), at any depth."""
    if isinstance(obj, dict):
        return {k: stable(v) for k, v in obj.items() if not _volatile(str(k))}
    if isinstance(obj, (list, tuple)):
        return [stable(v) for v in obj]
    return obj


def differences(a: Any, b: Any, path: str = "", out: list[str] | None = None, limit: int = 8) -> list[str]:
    """Where two states differ (up to ``limit`` paths): dict keys, list lengths, values; tensors and
    arrays by :func:`max_abs_diff` (a NaN anywhere is a difference); float NaN equals NaN."""
    import numpy as np
    import torch

    out = [] if out is None else out
    if len(out) >= limit:
        return out
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            out.append(f"{path or '.'}: keys {sorted(map(str, set(a) ^ set(b)))[:5]} in one only")
        for k in a.keys() & b.keys():
            differences(a[k], b[k], f"{path}/{k}", out, limit)
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            out.append(f"{path}: {len(a)} entries vs {len(b)}")
        for i, (x, y) in enumerate(zip(a, b)):
            differences(x, y, f"{path}[{i}]", out, limit)
    elif isinstance(a, (torch.Tensor, np.ndarray)) or isinstance(b, (torch.Tensor, np.ndarray)):
        d = max_abs_diff(a, b)
        if d != 0.0:
            out.append(f"{path}: max |diff| {d:g}")
    elif isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        pass
    elif type(a) is not type(b) and not (isinstance(a, (int, float)) and isinstance(b, (int, float))):
        out.append(f"{path}: {type(a).__name__} vs {type(b).__name__}")
    elif a != b:
        out.append(f"{path}: {str(a)[:40]} vs {str(b)[:40]}")
    return out


#: The parts of a run's state that :func:`compare` checks besides assignments, episodes and weights.
STATE_PARTS = ("learners", "driver", "bank", "metrics", "eval")


def final_state(run_dir: Path) -> dict[str, Any]:
    """A finished run's whole state, from its newest checkpoint and its logs: assignments, logged
    episode indices and policy weights, and (:data:`STATE_PARTS`) every learner's whole state
    (weights, optimizer moments, schedule, version), the driver's counters and stream position, the bank
    (buffers, history, merges) and the service's counters, and the rows of metrics.jsonl and
    eval.jsonl, wall-clock fields (:func:`stable`) left out."""
    import numpy as np

    from ..clustering.persistence import STATE_FILE
    from ..runtime.checkpoint import latest_valid_checkpoint, load_state
    from ..runtime.clustering_service import ClusteringService
    from ..runtime.logfiles import read_jsonl_segments

    ckpt = latest_valid_checkpoint(run_dir, log=lambda *_: None)
    if ckpt is None:
        raise RuntimeError(f"{run_dir} has no valid checkpoint")
    cfg = load_run_config(ckpt / "config.yaml")
    service = ClusteringService(cfg, read_only=True)
    service.load(str(ckpt / "bank"))
    records = service.assignments(0, 10**9)
    weights = {
        int(f.stem.split("-")[1]): load_state(f, str(f))["ppo"]["model"]
        for f in sorted((ckpt / "learners").glob("policy-*.pt"))
    }
    logged = [int(r["episode_index"]) for r in read_jsonl_segments(run_dir, "episodes.jsonl")]
    learners = {f.stem: load_state(f, str(f)) for f in sorted((ckpt / "learners").glob("*.pt"))}
    bank_doc = json.loads((ckpt / "bank" / STATE_FILE).read_text())
    with np.load(ckpt / "bank" / bank_doc["buffers_file"], allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    service_doc = ckpt / "bank" / "service.json"
    bank = {"state": stable(bank_doc["state"]), "buffers": arrays,
            "service": stable(json.loads(service_doc.read_text())) if service_doc.is_file() else None}  # fmt: skip
    return {
        "learners": learners,
        "driver": stable(json.loads((ckpt / "driver.json").read_text())),
        "bank": bank,
        "metrics": stable(list(read_jsonl_segments(run_dir, "metrics.jsonl"))),
        "eval": stable(list(read_jsonl_segments(run_dir, "eval.jsonl"))),
        "assignments": [(int(r["policy_id"]), r["decision"]) for r in records],
        "assigned_episodes": [int(e) for r in records for e in r["episode_indices"]],
        "logged_episodes": logged,
        "weights": weights,
        "checkpoint": ckpt.name,
    }


def max_abs_diff(a: Any, b: Any) -> float:
    """The largest ``|a - b|`` of two tensors, with nothing hidden: 0.0 only when they are equal
    element by element; NaN when either holds a NaN (NaN is never greater than anything, so a
    running ``max()`` would drop it); inf where an inf meets anything but the same inf, or the
    shapes differ."""
    import torch

    a = torch.as_tensor(a).detach().to("cpu", torch.float64)
    b = torch.as_tensor(b).detach().to("cpu", torch.float64)
    if a.shape != b.shape:
        return math.inf
    if bool(a.isnan().any()) or bool(b.isnan().any()):
        return math.nan
    diff = (a - b).abs()
    diff[a == b] = 0.0  # equal infs (inf - inf is NaN)
    return float(diff.max()) if diff.numel() else 0.0


def compare(clean: dict[str, Any], other: dict[str, Any]) -> dict[str, Any]:
    """What differs between two runs' final states (see :func:`final_state`).

    Weights are identical only when both runs hold the same policies with the same parameter
    names and every tensor pair has :func:`max_abs_diff` 0.0; a NaN in either run's weights is a
    difference (``weights_max_abs_diff`` is then NaN and ``weights_with_nan`` names the tensors).
    """
    n = len(clean["assigned_episodes"])
    counts = Counter(other["logged_episodes"])
    same_keys = clean["weights"].keys() == other["weights"].keys() and all(
        w.keys() == other["weights"][pid].keys() for pid, w in clean["weights"].items()
    )
    diffs: dict[str, float] = {}
    if same_keys:
        for pid, w in clean["weights"].items():
            for name, t in w.items():
                diffs[f"{pid}/{name}"] = max_abs_diff(t, other["weights"][pid][name])
    with_nan = sorted(k for k, d in diffs.items() if math.isnan(d))
    max_diff = math.nan if with_nan else max(diffs.values(), default=0.0)
    state = {part: differences(clean.get(part), other.get(part)) for part in STATE_PARTS}
    return {
        "state_identical": not any(state.values()),
        "state_differences": {part: d for part, d in state.items() if d},
        "batches": len(clean["assignments"]),
        "assignments_identical": clean["assignments"] == other["assignments"],
        "assigned_exactly_once": sorted(other["assigned_episodes"]) == list(range(n)) == other["assigned_episodes"],
        "logged_exactly_once": sorted(counts) == list(range(n)) and set(counts.values()) == {1},
        "logged_doubles": sum(c - 1 for c in counts.values()),
        "logged_missing": n - len(set(counts) & set(range(n))),
        "policies": sorted(other["weights"]),
        "weights_identical": same_keys and not with_nan and max_diff == 0.0,
        "weights_max_abs_diff": max_diff if same_keys else None,
        "weights_with_nan": with_nan,
    }


STATE_PART_NAMES = {
    "learners": "learners' states (weights, optimizer moments, schedules, versions)",
    "driver": "driver's counters and stream position",
    "bank": "bank's buffers, history and counters",
    "metrics": "rows of metrics.jsonl",
    "eval": "rows of eval.jsonl",
}


def failures(report: dict[str, Any], kinds: set[str] | None = None) -> list[str]:
    """Why a report of :func:`run` fails its verdict (empty: it passes).

    The chaos run must equal the clean run (:func:`compare`) *and* its faults must have happened:
    every kind in ``kinds`` killed at least once (``report["kills"]``: kind -> count), and with
    ``--node-loss`` the node removed (``report["node_loss"]["node_removed"]``).
    """
    c = report["comparison"]
    out: list[str] = []
    if not c["assignments_identical"]:
        out.append("the assignments differ from the clean run's")
    if not c["assigned_exactly_once"]:
        out.append("not every episode was assigned exactly once")
    if not c["logged_exactly_once"]:
        out.append(f"not every episode was logged exactly once ({c['logged_doubles']} doubles, "
                   f"{c['logged_missing']} missing)")  # fmt: skip
    if not c["weights_identical"]:
        if c.get("weights_with_nan"):
            out.append(f"NaN in the final weights ({', '.join(c['weights_with_nan'][:5])})")
        elif c["weights_max_abs_diff"] is None:
            out.append(f"the policies or their parameters differ from the clean run's (chaos run: {c['policies']})")
        else:
            out.append(f"the final weights differ from the clean run's (max |diff| {c['weights_max_abs_diff']:g})")
    for part, where in c.get("state_differences", {}).items():
        out.append(f"the {STATE_PART_NAMES[part]} differ from the clean run's: {'; '.join(where[:3])}")
    if "kills" in report:
        kills = report["kills"]
        missing = [k for k in KINDS if k in (kinds if kinds is not None else kills) and kills.get(k, 0) < 1]
        if missing:
            counts = ", ".join(f"{k} {v}" for k, v in sorted(kills.items()))
            out.append(f"no {' / '.join(missing)} was killed; every kind in --kinds must be killed at least once "
                       f"(kills: {counts})")  # fmt: skip
    if "node_loss" in report and not report["node_loss"]["node_removed"]:
        n = report["node_loss"]
        out.append(f"the node holding the {n['lost']} was not removed (--lose-after {n.get('lose_after')})")
    return out


# ---- the chaos run --------------------------------------------------------------------------------
class ChaosRun:
    """``covers-dist train`` in a child process, killed and resumed as the schedule says."""

    def __init__(
        self, cfg_path: str, overrides: list[str], run_dir: Path, storage: str, log: Callable[[str], None]
    ) -> None:
        self.run_dir = run_dir
        self.storage = storage  # where the run's processes record themselves
        self.log = log
        sets = [x for o in overrides for x in ("--set", o)]
        self.first = ["train", "--config", cfg_path, *sets, "--run-dir", str(run_dir)]
        self.kills: Counter[str] = Counter()
        self.output = open(run_dir.parent / f"{run_dir.name}-driver.log", "a")
        self.proc: subprocess.Popen | None = None
        self.started = 0.0

    def _start(self, args: list[str]) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.started = time.time()
        self.proc = subprocess.Popen(  # its own process group: a driver-kill takes the Ray instance it starts too
            [sys.executable, "-m", "covers_dist", *args], stdout=self.output, stderr=subprocess.STDOUT, env=env,
            start_new_session=True,
        )  # fmt: skip

    def _records(self) -> list[dict[str, Any]]:
        return list_processes(self.storage)

    def _victims(self, kinds: set[str]) -> dict[str, list[dict[str, Any]]]:
        """Live processes of the current driver's run, by kind."""
        out: dict[str, list[dict[str, Any]]] = {}
        records = [r for r in self._records() if r["started"] >= self.started and running(int(r["pid"]))]
        for kind in kinds:
            role = ROLE.get(kind, kind)
            for rec in records:
                if rec["role"] == role and (role != "driver" or rec["pid"] == self.proc.pid):
                    out.setdefault(kind, []).append(rec)
        return out

    def _driver_ready(self) -> bool:
        return any(r["role"] == "driver" and r["pid"] == self.proc.pid for r in self._records())

    def _result(self) -> dict[str, Any]:
        """The JSON line ``covers-dist train`` prints last."""
        text = (self.run_dir.parent / f"{self.run_dir.name}-driver.log").read_text().splitlines()
        for line in reversed(text):
            if line.startswith("{") and '"status"' in line:
                return json.loads(line)
        return {}

    def _check_exit(self, what: str, allowed: tuple[int, ...] = (0,)) -> None:
        assert self.proc is not None
        if self.proc.returncode not in allowed:
            tail = "\n".join((self.run_dir.parent / f"{self.run_dir.name}-driver.log").read_text().splitlines()[-30:])
            raise RuntimeError(f"the driver exited with {self.proc.returncode} after {what}; its output:\n{tail}")

    def run(self, rng: random.Random, interval: tuple[float, float], kinds: set[str], max_kills: int) -> float:
        t0 = time.monotonic()
        self._start(self.first)
        while True:
            assert self.proc is not None
            while not self._driver_ready() and self.proc.poll() is None:
                time.sleep(0.1)
            try:
                self.proc.wait(rng.uniform(*interval))
            except subprocess.TimeoutExpired:
                pass
            if self.proc.poll() is not None:
                self._check_exit("running")
                if self._result().get("status") == "finished":
                    break
                self._start(["train", "--resume", str(self.run_dir)])  # stopped by a signal before we knew
                continue
            if max_kills and sum(self.kills.values()) >= max_kills:
                continue
            victims = self._victims(kinds)
            if max_kills:  # the kills left are needed for the kinds not killed yet: only those
                unkilled = {k for k in kinds if not self.kills[k]}
                if max_kills - sum(self.kills.values()) <= len(unkilled):
                    victims = {k: v for k, v in victims.items() if k in unkilled}
            if not victims:
                continue
            kind = rng.choice(sorted(victims))
            rec = rng.choice(sorted(victims[kind], key=lambda r: r["pid"]))
            self._kill(kind, rec)
        self.output.close()
        return time.monotonic() - t0

    def _kill(self, kind: str, rec: dict[str, Any]) -> None:
        assert self.proc is not None
        name = kind if rec.get("index") is None else f"{kind}-{rec['index']}"
        if kind == "driver-kill":
            left = [r for r in self._records() if r["started"] >= self.started and r["pid"] != self.proc.pid]
            os.killpg(self.proc.pid, signal.SIGKILL)  # the driver, and the Ray head it started, at once
            self.proc.wait(60)
            self._reap(left)
            self.kills[kind] += 1
            self.log(f"kill {sum(self.kills.values()):3d}: driver (pid {self.proc.pid}, SIGKILL of its process group); "
                     "resuming")  # fmt: skip
            self._start(["train", "--resume", str(self.run_dir)])
            return
        if kind == "driver":
            os.kill(rec["pid"], signal.SIGTERM)
            self.proc.wait(600)
            # 0: it checkpointed and exited; 15: the signal came while ray.init held its own handler
            # (nothing to save yet); -15: it came while the interpreter was finalising, after the run
            # had ended (Python has restored the default action by then): all are resumed
            self._check_exit("SIGTERM", allowed=(0, 15, -signal.SIGTERM))
            status = self._result().get("status")
            self.kills[kind] += 1
            self.log(f"kill {sum(self.kills.values()):3d}: driver (SIGTERM, exit {status or self.proc.returncode}); resuming")
            if status != "finished":
                self._start(["train", "--resume", str(self.run_dir)])
            return
        try:
            os.kill(rec["pid"], signal.SIGKILL)
        except ProcessLookupError:
            return
        self.kills[kind] += 1
        self.log(f"kill {sum(self.kills.values()):3d}: {name} (pid {rec['pid']}, SIGKILL)")


    def _reap(self, records: list[dict[str, Any]], timeout_s: float = 30.0) -> None:
        """Wait for the processes a killed driver started (workers, learners, the clustering actor,
        the HTTP service) to go with it; SIGKILL, by PID, any still running after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and any(running(int(r["pid"])) for r in records):
            time.sleep(0.2)
        for r in records:
            if running(int(r["pid"])):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(int(r["pid"]), signal.SIGKILL)


# ---- node loss ------------------------------------------------------------------------------------
def node_loss_run(
    cfg: Config, lose: str, lose_after: int, log: Callable[[str], None], hide: list[Path] | None = None
) -> dict[str, Any]:
    """The run on a 2-node loopback cluster whose node holding the ``lose`` actors is removed mid-run.

    ``hide``: the second node shares no disk with the driver: it runs in its own mount namespace
    with an empty tmpfs over each of these directories (:meth:`LocalCluster.add_isolated_node`).

    Placement is forced with placeholder actors that hold every free CPU of a node while the run's
    actors are placed: the rollout workers (``workers``) or the learners (``learners``, which then
    reserve one CPU each) land on the second node. Before that node is removed, the head's
    placeholders go, so the surviving head has room for everything that restarts.
    """
    import dataclasses

    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    from ..runtime.driver import Trainer
    from ..runtime.local_cluster import LocalCluster

    workers = cfg.runtime.num_workers
    learner_cpus = 1 if lose == "learners" else 0
    room = 4  # learners the head can take when the second node is gone
    cfg = dataclasses.replace(cfg, runtime=dataclasses.replace(cfg.runtime, learner_num_cpus=learner_cpus))

    @ray.remote(num_cpus=0)
    class Placeholder:
        def ready(self) -> bool:
            return True

    def hold(node_id: str, cpus: int) -> Any:
        strategy = NodeAffinitySchedulingStrategy(node_id, soft=False)
        actor = Placeholder.options(num_cpus=cpus, scheduling_strategy=strategy).remote()
        ray.get(actor.ready.remote())
        return actor

    head_cpus = workers + room
    storage = storage_location(cfg)
    with LocalCluster(head_cpus) as cluster:
        cfg = dataclasses.replace(cfg, runtime=dataclasses.replace(cfg.runtime, ray_address=cluster.address))
        ray.init(address=cluster.address, log_to_driver=False)
        cpus = workers if lose == "workers" else room
        node = cluster.add_isolated_node(cpus, hide) if hide else cluster.add_node(cpus)
        head_id, other_id = cluster.head.node_id, node.node_id
        if lose == "workers":
            holders = [hold(head_id, head_cpus)]  # the workers go to the other node
        else:
            holders = [hold(other_id, room), hold(head_id, room)]  # workers on the head
        trainer = Trainer(cfg, log=lambda *_: None)
        ray.get([w.pid.remote() for w in trainer.backend.workers])
        if lose == "learners":
            ray.kill(holders.pop(0))  # the other node is now free for the learners only
        removed = threading.Event()
        ended = threading.Event()
        before: dict[str, str] = {}

        def lose_node() -> None:
            while trainer.iteration < lose_after:
                if ended.is_set():  # the run ended first: the node stays (the verdict says so)
                    log(f"the run ended after iteration {trainer.iteration}, before the node could go")
                    return
                time.sleep(0.05)
            before.update({_name(r): r.get("node", "") for r in list_processes(storage)})
            for h in holders:
                ray.kill(h)
            cluster.remove_node(node)
            removed.set()
            log(f"removed the node holding the {lose} after iteration {lose_after}")

        killer = threading.Thread(target=lose_node, daemon=True)
        killer.start()
        t0 = time.monotonic()
        try:
            trainer.run()
        finally:
            ended.set()
            trainer.close()
        killer.join(5)
        after = {_name(r): r.get("node", "") for r in list_processes(storage)}
        return {
            "lost": lose,
            "lose_after": lose_after,
            "node_removed": removed.is_set(),
            "on_lost_node": sorted(n for n, where in before.items() if where == other_id),
            "moved_to_head": sorted(n for n, where in after.items() if before.get(n) == other_id and where == head_id),
            "wall_s": round(time.monotonic() - t0, 1),
            "isolated_disk": bool(hide),
        }


def _name(rec: dict[str, Any]) -> str:
    return rec["role"] if rec.get("index") is None else f"{rec['role']}-{rec['index']}"


# ---- the command ----------------------------------------------------------------------------------
def _fail(message: str) -> NoReturn:
    """A one-line usage error on stderr, exit status 2."""
    print(f"{PROG}: {message}", file=sys.stderr)
    raise SystemExit(2)


def _interval(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        _fail(f"--interval must be MIN,MAX seconds, got {text!r}")
    if not 0 < lo <= hi:
        _fail(f"--interval needs 0 < MIN <= MAX, got {text!r}")
    return lo, hi


def run_iterations(cfg: Config) -> int:
    """Iterations of a run of ``cfg``: each takes ``clustering.update_every`` episodes of
    ``env.max_episode_steps`` env steps (no environment ends an episode early), until
    ``runtime.total_env_steps``."""
    per_iteration = cfg.steps_per_update
    return -(-cfg.runtime.total_env_steps // per_iteration)


def _check_lose_after(lose_after: int, cfg: Config) -> None:
    """``--lose-after`` must name an iteration the run completes with more to go, or the node never goes."""
    n = run_iterations(cfg)
    if not 1 <= lose_after <= n - 1:
        _fail(
            f"--lose-after {lose_after} is impossible: the run has {n} iterations "
            f"(runtime.total_env_steps={cfg.runtime.total_env_steps} / (clustering.update_every="
            f"{cfg.clustering.update_every} * env.max_episode_steps={cfg.env.max_episode_steps})), so the node "
            f"can go only after iteration 1 to {n - 1}" + ("" if n >= 2 else " (none: lengthen the run)")
        )


def _jsonable(x: Any) -> Any:
    """``x`` with NaN and infinities as strings (strict JSON has no such numbers)."""
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def run(args: argparse.Namespace) -> int:
    interval = _interval(args.interval)
    kinds = {k.strip() for k in args.kinds.split(",") if k.strip()}
    if not kinds or kinds - set(KINDS):
        _fail(f"--kinds must name some of {', '.join(KINDS)}, got {args.kinds!r}")
    if not args.node_loss and (args.max_kills < 0 or 0 < args.max_kills < len(kinds)):
        _fail(f"--max-kills {args.max_kills} cannot kill each of the {len(kinds)} kinds in --kinds "
              f"({','.join(sorted(kinds))}) once: give 0 (no limit) or at least {len(kinds)}")  # fmt: skip
    base = load_config(args.config, args.overrides)  # validates the config before anything runs
    if args.node_loss:
        _check_lose_after(args.lose_after, base)
    if args.isolated_disk and not args.node_loss:
        _fail("--isolated-disk goes with --node-loss (the second node of the 2-node cluster is the isolated one)")
    if args.isolated_disk and not (base.runtime.storage and is_uri(base.runtime.storage)):
        _fail("--isolated-disk needs --set runtime.storage=URI (e.g. s3://bucket/prefix): the isolated node cannot "
              "see a local path, and the run's state must reach every node")  # fmt: skip
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="covers-chaos-"))
    out.mkdir(parents=True, exist_ok=True)
    log = (lambda m: print(m, file=sys.stderr, flush=True)) if args.json else (lambda m: print(m, flush=True))
    def own_storage(name: str) -> list[str]:  # each run its own part of a given storage
        return [f"runtime.storage={storage_child(base.runtime.storage, name)}"] if base.runtime.storage else []

    serial = [*args.overrides, "runtime.serial=true", f"runtime.run_dir={out / 'clean'}", "api.enabled=false",
              *own_storage("clean")]  # fmt: skip
    log(f"clean run ({base.runtime.total_env_steps} env steps, serial) in {out / 'clean'}")
    quiet = contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()
    with quiet:  # progress lines of the runs in this process: not on stdout when it carries JSON
        clean_s = clean_run(load_config(args.config, serial))
    report: dict[str, Any] = {"config": args.config, "seed": base.seed, "clean_wall_s": round(clean_s, 1)}
    chaos_dir = out / ("node-loss" if args.node_loss else "chaos")
    if args.node_loss:
        sets = [*args.overrides, "runtime.serial=false", f"runtime.run_dir={chaos_dir}", *own_storage(chaos_dir.name)]
        cfg = load_config(args.config, sets)
        with quiet:
            hide = [out] if args.isolated_disk else None
            report["node_loss"] = node_loss_run(cfg, args.node_loss, args.lose_after, log, hide)
    else:
        chaos = [*args.overrides, "runtime.serial=false", "api.enabled=true", "api.port=0", *own_storage(chaos_dir.name)]
        storage = storage_location(load_config(args.config, [*chaos, f"runtime.run_dir={chaos_dir}"]))
        runner = ChaosRun(args.config, chaos, chaos_dir, storage, log)
        log(f"chaos run in {chaos_dir}: a kill every {interval[0]:g}-{interval[1]:g} s among {sorted(kinds)}")
        report["chaos_wall_s"] = round(runner.run(random.Random(args.seed), interval, kinds, args.max_kills), 1)
        report["kinds"] = sorted(kinds)
        report["kills"] = {k: runner.kills[k] for k in KINDS if k in kinds or runner.kills[k]}
        report["kills_total"] = sum(runner.kills.values())
    report["comparison"] = compare(final_state(out / "clean"), final_state(chaos_dir))
    report["out"] = str(out) if args.out else None
    c = report["comparison"]
    same = ("assignments_identical", "weights_identical", "assigned_exactly_once", "logged_exactly_once",
            "state_identical")  # fmt: skip
    report["equal_to_clean"] = all(bool(c[k]) for k in same)
    if "kills_total" in report:
        report["target_kills"] = TARGET_KILLS
    report["failures"] = failures(report, None if args.node_loss else kinds)
    report["verdict"] = not report["failures"]
    ok = report["verdict"]
    if args.json:
        for reason in report["failures"]:  # the reasons on stderr too, where the progress lines go
            log(f"FAIL: {reason}")
        print(json.dumps(_jsonable(report)))
    else:
        _print(report)
    if not args.out:
        import shutil

        shutil.rmtree(out, ignore_errors=True)
    return 0 if ok else 1


def _print(r: dict[str, Any]) -> None:
    c = r["comparison"]
    print(f"clean run: {r['clean_wall_s']} s (serial)")
    if "kills" in r:
        kinds = ", ".join(f"{k} {v}" for k, v in r["kills"].items())
        print(f"chaos run: {r['chaos_wall_s']} s, {r['kills_total']} kills ({kinds}); target >= {TARGET_KILLS}")
    if "node_loss" in r:
        n = r["node_loss"]
        disk = ", isolated disk" if n.get("isolated_disk") else ""
        print(f"node loss ({n['lost']}{disk}): removed={n['node_removed']} on the lost node: {n['on_lost_node']} "
              f"restarted on the head: {n['moved_to_head']} ({n['wall_s']} s)")  # fmt: skip
    print(
        f"{c['batches']} batches: assignments identical {c['assignments_identical']}, every episode assigned once "
        f"{c['assigned_exactly_once']}, logged once {c['logged_exactly_once']} (doubles {c['logged_doubles']}, "
        f"missing {c['logged_missing']}), weights identical {c['weights_identical']} (max |diff| "
        f"{c['weights_max_abs_diff']}) for policies {c['policies']}"
    )
    print("EQUAL to the clean run" if r["equal_to_clean"] else "DIFFERENT from the clean run")
    for reason in r["failures"]:
        print(f"FAIL: {reason}")
    print("verdict: PASS" if r["verdict"] else "verdict: FAIL")
