"""The markdown tables of the docs, from committed result files.

Each kind takes the paths of its files and returns one table (a string ending in a newline):

- ``stream``: run result files (:func:`~covers_dist.results.summary.summarize`), one row a run;
- ``headline``: the same files, one row per run label over its seeds (the README's table);
- ``features`` and ``distances``: ``covers-dist bench features --json`` output (JSON lines);
- ``assign``: ``covers-dist bench assign --stream --json`` rows;
- ``ablate``: ``covers-dist bench ablate --json`` output (its cell rows).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

from .summary import ResultError


def _rows(paths: list[str]) -> list[dict[str, Any]]:
    out = []
    for p in paths:
        out += [json.loads(line) for line in Path(p).read_text().splitlines() if line.strip()]
    return out


def _f(v: Any, digits: int = 2) -> str:
    return "n/a" if v is None else f"{float(v):.{digits}f}"


def _table(head: list[str], body: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(row) + " |" for row in body]
    return "\n".join(lines) + "\n"


def stream(paths: list[str]) -> str:
    """One row per run: per group mean / worst trainable copy / worst held-out copy (report
    split, greedy, each episode's own choice), policies, ARI, env steps, minutes, seed and role."""
    data = [json.loads(Path(p).read_text()) for p in paths]
    for p, d in zip(paths, data):
        if "report" not in d or "groups" not in d["report"]:
            raise ResultError(f"{p}: not a run result file (no report.groups)")
    tasks = list(dict.fromkeys(t for d in data for t in d["report"]["groups"]))
    head = ["run", "seed (role)", *[f"{t} mean / worst / held-out" for t in tasks], "policies (created)", "ARI",
            "env steps (stopped by)", "minutes", "episodes per pair"]  # fmt: skip
    body = []
    for d in data:
        cells = []
        for t in tasks:
            g = d["report"]["groups"].get(t)
            cells.append("" if g is None else f"{_f(g['mean'])} / {_f(g['worst'])} / {_f(g['held_out_worst'])}")
        body.append([
            d["label"], f"{d['seed']} ({d['role']})", *cells, f"{d['policies']} ({d['policies_created']})",
            _f(d["ari"], 3), f"{d['env_steps']:,} ({d.get('stopped', 'n/a')})", f"{d['training_minutes']:.1f}", str(d["report"]["episodes_per_pair"]),
        ])  # fmt: skip
    return _table(head, body)


def _steps(n: float) -> str:
    if n >= 1e6:
        return f"{n / 1e6:.2f}M"
    return f"{n / 1e3:.1f}k" if n >= 1e3 else f"{n:g}"


def _span(values: list[float], fmt: Callable[[float], str]) -> str:
    lo, hi = min(values), max(values)
    return fmt(lo) if fmt(lo) == fmt(hi) else f"{fmt(lo)}-{fmt(hi)}"


def headline(paths: list[str]) -> str:
    """One row per run label over its seeds: the README's results table. Per label: the mean
    success over every trainable (task, g) and seed, the worst pair, how many seeds held every
    trainable and held-out pair >= 0.9, policies and ARI, the budget, env steps and minutes used."""
    data = [json.loads(Path(p).read_text()) for p in paths]
    by_label: dict[str, list[dict[str, Any]]] = {}
    for p, d in zip(paths, data):
        if "report" not in d or "groups" not in d["report"]:
            raise ResultError(f"{p}: not a run result file (no report.groups)")
        by_label.setdefault(d["label"], []).append(d)
    body = []
    for label, runs in by_label.items():
        pairs = [q for d in runs for g in d["report"]["groups"].values() for q in g["pairs"]["trainable"]]
        held = [q for d in runs for g in d["report"]["groups"].values() for q in g["pairs"]["held_out"]]
        mean = sum(q["success"] for q in pairs) / len(pairs)
        worst = min(q["success"] for q in pairs + held)
        solved = sum(
            all(q["success"] >= 0.9 for g in d["report"]["groups"].values() for q in g["pairs"]["trainable"] + g["pairs"]["held_out"])
            for d in runs
        )
        roles = sorted({d["role"] for d in runs})
        budget = runs[0]["budget"]
        limit = f"{_steps(budget['env_steps'])} env steps" + (f" or {budget['minutes']:g} min" if budget.get("minutes") else "")
        tasks = runs[0]["tasks"]
        what = f"{len(tasks)} groups under {runs[0]['group']}" if len(tasks) > 1 else f"{tasks[0]} under {runs[0]['group']}"
        body.append([
            label, what,
            f"mean {mean:.2f}, worst (task, g) {worst:.2f}; every pair >= 0.9 on {solved} of {len(runs)} seeds",
            f"{_span([d['policies'] for d in runs], str)} policies, ARI {_span([d['ari'] for d in runs], lambda v: f'{v:.2f}')}",
            f"{', '.join(str(d['seed']) for d in runs)} ({'/'.join(roles)})",
            limit,
            f"{_span([d['env_steps'] for d in runs], _steps)}, {_span([d['training_minutes'] for d in runs], lambda v: f'{v:.0f}')} min "
            f"(stopped by: {', '.join(sorted({d.get('stopped', 'n/a') for d in runs}))})",
            "; ".join(sorted({d["cpu"] for d in runs})),
        ])  # fmt: skip
    head = ["run", "task", "greedy success (report split)", "bank", "seeds (role)", "budget", "used", "CPU"]
    return _table(head, body)


def features(paths: list[str]) -> str:
    data = _rows(paths)
    candidates = list(dict.fromkeys(r["candidate"] for r in data))
    body = []
    for steps in sorted({r["env_steps"] for r in data}):
        cells = []
        for c in candidates:
            r = next((r for r in data if r["env_steps"] == steps and r["candidate"] == c), None)
            cells.append("" if r is None else f"{_f(r['separation'], 1)}x / {_f(r['correct'])}")
        body.append([f"{steps:,}", *cells])
    return _table(["env steps", *[f"{c}: separation / correct" for c in candidates]], body)


def distances(paths: list[str]) -> str:
    body = []
    for r in sorted(_rows(paths), key=lambda r: (r["env_steps"], r["candidate"])):
        same, other = list(r["same_group_distance"].values()), list(r["nearest_other_distance"].values())
        body.append([f"{r['env_steps']:,}", r["candidate"], f"{_f(min(same))}-{_f(max(same))}", f"{_f(min(other))}-{_f(max(other))}"])
    head = ["env steps", "features", "same group: median W1 per policy (min-max)", "nearest other group (min-max)"]
    return _table(head, body)


def assign(paths: list[str]) -> str:
    body = []
    for r in _rows(paths):
        body.append([
            r["stream"], r["feature_source"], str(r["seed"]), f"{r['env_steps']:,}",
            f"{r['policies']} ({r.get('policies_created', r['policies'])})", str(r["true_groups"]), str(r.get("merges", 0)),
            _f(r["ari"], 3), _f(r["wrong_policy_fraction"], 3), f"{r['wall_s']:.0f}",
        ])  # fmt: skip
    head = ["stream", "features", "seed", "env steps", "policies (created)", "true groups", "merges", "ARI",
            "wrong-policy episodes", "wall s"]  # fmt: skip
    return _table(head, body)


def ablate(paths: list[str]) -> str:
    body = []
    for r in _rows(paths):
        if "seeds" not in r:  # a run row; the cell rows follow them
            continue
        body.append([
            r["cell"], ",".join(map(str, r["seeds"])), _f(r["policies_created"], 1), _f(r["false_splits"], 1),
            _f(r["merges"], 1), f"{_f(r['ari'], 3)} / {_f(r['ari_min'], 3)}", _f(r["wrong_policy_fraction"], 3),
        ])  # fmt: skip
    head = ["cell", "seeds", "policies created", "false splits", "merges", "ARI (mean / min)", "wrong-policy episodes"]
    return _table(head, body)


KINDS: dict[str, Callable[[list[str]], str]] = {
    "headline": headline,
    "stream": stream,
    "features": features,
    "distances": distances,
    "assign": assign,
    "ablate": ablate,
}
