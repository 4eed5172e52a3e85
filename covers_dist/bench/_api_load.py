"""The load generator of ``covers-dist bench api`` and its measurements.

:func:`run_load` sends a planned, rate-bounded load from a fresh process (``spawn``): for every
endpoint of the plan, ``concurrency`` clients, each paced to its share of the endpoint's rate and
spread evenly over the period. Latency is the time from sending a request to its full answer.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from typing import Any

__all__ = ["run_load", "summarize", "server_time", "server_ms", "process_cpu_s"]


async def _client_loop(
    client: Any, method: str, path: str, body: Any, period: float, phase: float, end: float, out: list
) -> None:
    import asyncio

    next_t = time.monotonic() + phase - period  # clients are spread evenly over the period
    while True:
        next_t += period
        now = time.monotonic()
        if now >= end:
            return
        if next_t > now:
            await asyncio.sleep(next_t - now)
        t0 = time.perf_counter()
        try:
            r = await client.request(method, path, json=body)
            outcome = "ok" if r.status_code < 400 else str(r.status_code)
        except Exception as e:  # noqa: BLE001 - a failed request counts as an error, by kind
            outcome = type(e).__name__
        out.append((time.perf_counter() - t0, outcome))


async def _load(url: str, plan: list[dict[str, Any]], duration: float) -> dict[str, Any]:
    import asyncio

    import httpx

    results: dict[str, list] = {p["name"]: [] for p in plan}
    limits = httpx.Limits(max_connections=sum(p["concurrency"] for p in plan))
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=30) as client:
        await client.get("/healthz")
        t_start, cpu_start = time.time(), time.process_time()
        end = time.monotonic() + duration
        tasks = []
        for p in plan:
            period = p["concurrency"] / p["rate"]
            for k in range(p["concurrency"]):
                args = (p["method"], p["path"], p.get("body"), period, period * (k + 0.5) / p["concurrency"])
                tasks.append(_client_loop(client, *args, end, results[p["name"]]))
        await asyncio.gather(*tasks)
        t_end, cpu = time.time(), time.process_time() - cpu_start
    return {"t_start": t_start, "t_end": t_end, "results": results, "client_cpu_s": cpu}


def _load_process(url: str, plan: list[dict[str, Any]], duration: float, queue: Any) -> None:
    import asyncio

    queue.put(asyncio.run(_load(url, plan, duration)))


def run_load(url: str, plan: list[dict[str, Any]], duration: float) -> dict[str, Any]:
    """Send the planned load from a fresh process for ``duration`` seconds; its raw results."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_load_process, args=(url, plan, duration, queue), daemon=True)
    proc.start()
    out = queue.get(timeout=duration + 120)
    proc.join(30)
    return out


def server_time(url: str) -> dict[str, tuple[float, float]]:
    """(seconds, requests) answered so far per route, from the service's own histogram."""
    import httpx
    from prometheus_client.parser import text_string_to_metric_families

    out: dict[str, list[float]] = {}
    for fam in text_string_to_metric_families(httpx.get(f"{url}/metrics", timeout=30).text):
        if fam.name != "covers_api_request_duration_seconds":
            continue
        for s in fam.samples:
            key = f"{s.labels['method']} {s.labels['route']}"
            if s.name.endswith("_sum"):
                out.setdefault(key, [0.0, 0.0])[0] += s.value
            elif s.name.endswith("_count"):
                out.setdefault(key, [0.0, 0.0])[1] += s.value
    return {k: (v[0], v[1]) for k, v in out.items()}


def server_ms(before: dict, after: dict, name: str) -> float | None:
    (s0, n0), (s1, n1) = before.get(name, (0.0, 0.0)), after.get(name, (0.0, 0.0))
    return round(1e3 * (s1 - s0) / (n1 - n0), 2) if n1 > n0 else None


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` so far (Linux /proc; None elsewhere)."""
    try:
        fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def summarize(name: str, samples: list[tuple[float, str]], seconds: float) -> dict[str, Any]:
    """p50/p99 latency (ms) of the successful requests, requests/s and errors (by kind)."""
    lat = sorted(s * 1e3 for s, outcome in samples if outcome == "ok")
    kinds: dict[str, int] = {}
    for _, outcome in samples:
        if outcome != "ok":
            kinds[outcome] = kinds.get(outcome, 0) + 1

    def pct(q: float) -> float | None:
        return round(lat[min(len(lat) - 1, int(q * len(lat)))], 2) if lat else None

    return {
        "endpoint": name,
        "requests": len(samples),
        "errors": sum(kinds.values()),
        "error_kinds": kinds,
        "requests_per_s": round(len(samples) / seconds, 1),
        "p50_ms": pct(0.50),
        "p99_ms": pct(0.99),
    }
