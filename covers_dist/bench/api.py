"""``covers-dist bench api``: latency and throughput of the HTTP service, and what it costs training.

One run, on a local loopback-only Ray instance:

1. a smoke-config training run steps in a background thread of this process (the Trainer the
   CLI runs); the HTTP service runs in a process of its own (``start_api_server`` with the
   clustering actor, i.e. ``covers-dist serve --address``), as a training run starts it;
2. alternating windows without and with API load, while training runs: the load comes from a
   second process on 127.0.0.1 that sends ``GET /v1/assignments/latest`` and ``POST /v1/act`` at bounded
   rates (a fixed number of concurrent clients, each paced to its share of the rate);
3. training stops, and one more loaded window measures the service idle.

``GET /healthz`` at 10 requests/s runs along as the floor: a request with no work behind it,
showing what the machine's scheduling alone adds to latency at that moment.

It reports latency p50/p99 and requests/s per endpoint and scenario, and training env steps/s
with and without the load (medians over windows; the ratio is measured in this one run).
Targets: p99 <= 20 ms for GET /v1/assignments/latest while training runs; env steps/s under load >= 0.9x.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import tempfile
import threading
import time
from typing import Any

from ._api_load import process_cpu_s, run_load, server_ms, server_time, summarize

TARGET_P99_MS = 20.0
TARGET_RATIO = 0.9
ASSIGNMENT, ACT, FLOOR = "GET /v1/assignments/latest", "POST /v1/act", "GET /healthz"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("api", help="HTTP service latency and req/s, idle and while training (and its cost to training)")
    p.add_argument("--config", default="configs/smoke.yaml", help="training config (default: configs/smoke.yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, e.g. --set runtime.actor_nice=10 (repeatable)")
    p.add_argument("--window", type=float, default=20.0, help="seconds per measurement window (default: 20)")
    p.add_argument("--repeats", type=int, default=3, help="(no load, load) window pairs while training (default: 3)")
    p.add_argument("--rate", type=float, default=20.0, help="GET /v1/assignments/latest requests/s (default: 20)")
    p.add_argument("--act-rate", type=float, default=5.0, help="POST /v1/act requests/s (default: 5)")
    p.add_argument("--concurrency", type=int, default=4, help="concurrent clients per endpoint (default: 4)")
    p.add_argument("--json", action="store_true", help="print one JSON object per line")
    p.set_defaults(func=run)


# ---- training in the background ------------------------------------------------------------------
class BackgroundTraining:
    """Steps a Trainer in a thread and records (time, env steps) after every iteration."""

    def __init__(self, trainer: Any) -> None:
        self.trainer = trainer
        self.marks: list[tuple[float, int]] = []
        self.stop_event = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._loop, name="bench-training", daemon=True)

    def _loop(self) -> None:
        try:
            while not self.stop_event.is_set():
                row = self.trainer.step()
                self.trainer.backend.call_clustering("report", row)
                self.marks.append((time.time(), self.trainer.env_steps))
        except BaseException as e:  # noqa: BLE001 - reported by the main thread
            self.error = e

    def rate(self, t0: float, t1: float) -> float | None:
        """Env steps/s over the iterations that finished within [t0, t1]."""
        inside = [(t, s) for t, s in self.marks if t0 <= t <= t1]
        if len(inside) < 2:
            return None
        (ta, sa), (tb, sb) = inside[0], inside[-1]
        return (sb - sa) / (tb - ta)

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join()


def _progress(msg: str) -> None:
    print(f"[bench api] {msg}", file=sys.stderr, flush=True)


class Windows:
    """Alternating measurement windows while training runs: free, loaded, free, ..., free."""

    def __init__(self, url: str, pid: int, training: BackgroundTraining, plan: list[dict], window: float) -> None:
        self.url, self.pid, self.training, self.plan, self.window = url, pid, training, plan, window
        self.free: list[float | None] = []
        self.loaded: list[float | None] = []
        self.latencies: dict[str, list] = {p["name"]: [] for p in plan}
        self.server_means: list[dict[str, float | None]] = []
        self.api_cpu: list[float] = []  # CPU seconds per second of the service's process under load
        self.client_cpu: list[float] = []  # likewise for the load generator

    def free_window(self) -> None:
        t0 = time.time()
        time.sleep(self.window)
        self.free.append(self.training.rate(t0, time.time()))

    def loaded_window(self) -> dict[str, Any]:
        before, cpu0 = server_time(self.url), process_cpu_s(self.pid)
        out = run_load(self.url, self.plan, self.window)
        after, cpu1 = server_time(self.url), process_cpu_s(self.pid)
        seconds = out["t_end"] - out["t_start"]
        if cpu0 is not None and cpu1 is not None:
            self.api_cpu.append((cpu1 - cpu0) / seconds)
        self.client_cpu.append(out["client_cpu_s"] / seconds)
        self.server_means.append({n: server_ms(before, after, n) for n in self.latencies})
        self.loaded.append(self.training.rate(out["t_start"], out["t_end"]))
        for name in self.latencies:
            self.latencies[name] += out["results"][name]
        return out

    def training_row(self) -> dict[str, Any]:
        """Env steps/s without and with load; the ratio compares each loaded window with the mean
        of the free windows on either side (robust to slow drift), median over windows."""
        ratios = []
        for i, under in enumerate(self.loaded):
            around = [f for f in self.free[i : i + 2] if f]
            if under and around:
                ratios.append(under / statistics.mean(around))
        free = [f for f in self.free if f]
        loaded = [x for x in self.loaded if x]

        def mean(xs: list[float]) -> float | None:
            return round(statistics.mean(xs), 3) if xs else None

        return {
            "scenario": "training",
            "env_steps_per_s_without_api_load": round(statistics.median(free), 1) if free else None,
            "env_steps_per_s_with_api_load": round(statistics.median(loaded), 1) if loaded else None,
            "ratio": round(statistics.median(ratios), 3) if ratios else None,
            "target_ratio": TARGET_RATIO,
            "windows_free": [None if f is None else round(f, 1) for f in self.free],
            "windows_loaded": [None if x is None else round(x, 1) for x in self.loaded],
            "api_process_cpu_s_per_s": mean(self.api_cpu),
            "load_client_cpu_s_per_s": mean(self.client_cpu),
        }


def _rows(plan: list[dict], windows: Windows, idle: dict[str, Any], idle_ms: dict, seconds: float) -> list[dict]:
    rows = []
    for p in plan:
        name = p["name"]
        trained = [w[name] for w in windows.server_means if w.get(name) is not None]
        idle_s = idle["t_end"] - idle["t_start"]
        trained_ms = statistics.mean(trained) if trained else None
        for scenario, row, server in (
            ("training", summarize(name, windows.latencies[name], seconds), trained_ms),
            ("idle", summarize(name, idle["results"][name], idle_s), idle_ms.get(name)),
        ):
            row = {"scenario": scenario, **row, "rate_limit": p["rate"], "concurrency": p["concurrency"]}
            row["server_mean_ms"] = None if server is None else round(server, 2)
            if name == ASSIGNMENT and scenario == "training":
                row["target_p99_ms"] = TARGET_P99_MS
            rows.append(row)
    return sorted(rows, key=lambda r: r["scenario"] != "training")


def _print_table(rows: list[dict], t: dict[str, Any]) -> None:
    nan = float("nan")
    print(f"{'scenario':9s} {'endpoint':20s} {'req/s':>7s} {'p50 ms':>8s} {'p99 ms':>8s} {'server ms':>9s} "
          f"{'errors':>6s}  (rate cap, clients)")
    for r in rows:
        print(f"{r['scenario']:9s} {r['endpoint']:20s} {r['requests_per_s']:7.1f} {r['p50_ms'] or nan:8.2f} "
              f"{r['p99_ms'] or nan:8.2f} {r['server_mean_ms'] or nan:9.2f} {r['errors']:6d}  "
              f"({r['rate_limit']:g}/s, {r['concurrency']})")
    print(f"training env steps/s: {t['env_steps_per_s_without_api_load']} without API load, "
          f"{t['env_steps_per_s_with_api_load']} with it: ratio {t['ratio']} (target >= {TARGET_RATIO})")
    print(f"CPU under load (of 2 cores here): service process {t['api_process_cpu_s_per_s']} s/s, "
          f"load generator {t['load_client_cpu_s_per_s']} s/s")


def run(args: argparse.Namespace) -> int:
    from ..api import observation_json, start_api_server
    from ..config import load_config
    from ..envs import make_task
    from ..runtime.driver import Trainer
    from ..runtime.ray_setup import init_ray, shutdown_ray

    if args.window <= 0 or args.repeats < 1 or args.rate <= 0 or args.act_rate <= 0 or args.concurrency < 1:
        raise SystemExit("covers-dist bench api: --window, --rate, --act-rate > 0; --repeats, --concurrency >= 1")
    run_dir = tempfile.mkdtemp(prefix="covers-bench-api-")
    overrides = [*args.overrides, "name=bench-api", f"runtime.run_dir={run_dir}", "runtime.total_env_steps=100000000"]
    cfg = load_config(args.config, overrides)
    cfg = dataclasses.replace(cfg, api=dataclasses.replace(cfg.api, port=0, token=None))
    obs, _ = make_task(cfg.env, cfg.env.tasks[0], "r", seed=0).reset(seed=0)
    act_body = {"observation": observation_json(obs["image"], obs["proprio"]), "policy_id": 0}
    plan = [
        {"name": ASSIGNMENT, "method": "GET", "path": "/v1/assignments/latest", "rate": args.rate,
         "concurrency": args.concurrency},
        {"name": ACT, "method": "POST", "path": "/v1/act", "body": act_body, "rate": args.act_rate,
         "concurrency": max(1, args.concurrency // 2)},
        # the floor: what any request costs on this machine at this moment (no work behind it)
        {"name": FLOOR, "method": "GET", "path": "/healthz", "rate": 10.0, "concurrency": 1},
    ]
    init_ray(cfg.runtime.num_cpus)
    trainer = Trainer(cfg, log=lambda *_: None)
    training = BackgroundTraining(trainer)
    handle = None
    try:
        _progress("starting training and the HTTP service (its own process)")
        trainer.start_policy(0)
        training.thread.start()
        handle = start_api_server(cfg, trainer.backend.clustering)
        while len(training.marks) < 5:  # warm-up; policy 0's weights reach the clustering actor at iteration 2
            if training.error:
                raise training.error
            time.sleep(0.5)
        windows = Windows(handle.url, handle.proc.pid, training, plan, args.window)
        total = 2 * args.repeats + 1
        for i in range(total):
            kind = "training under API load" if i % 2 else "training, no API load"
            _progress(f"window {i + 1}/{total}: {kind} ({args.window:g} s)")
            windows.loaded_window() if i % 2 else windows.free_window()
        if training.error:
            raise training.error
        training.stop()
        _progress(f"training stopped; idle window under API load ({args.window:g} s)")
        before = server_time(handle.url)
        idle = run_load(handle.url, plan, args.window)
        after = server_time(handle.url)
    finally:
        if training.thread.is_alive():
            training.stop()
        if handle is not None:
            handle.stop()
        trainer.close()
        shutdown_ray()
    idle_ms = {p["name"]: server_ms(before, after, p["name"]) for p in plan}
    rows = _rows(plan, windows, idle, idle_ms, args.repeats * args.window)
    training_row = windows.training_row()
    if args.json:
        for row in [*rows, training_row]:
            print(json.dumps(row))
    else:
        _print_table(rows, training_row)
    return 0
