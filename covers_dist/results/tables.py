"""The markdown tables of the docs, from committed result files.

Each kind takes the paths of its files and returns one table (a string ending in a newline):

- ``stream``: run result files (:func:`~covers_dist.results.summary.summarize`), one row a run;
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
            "env steps", "minutes", "episodes per pair"]  # fmt: skip
    body = []
    for d in data:
        cells = []
        for t in tasks:
            g = d["report"]["groups"].get(t)
            cells.append("" if g is None else f"{_f(g['mean'])} / {_f(g['worst'])} / {_f(g['held_out_worst'])}")
        body.append([
            d["label"], f"{d['seed']} ({d['role']})", *cells, f"{d['policies']} ({d['policies_created']})",
            _f(d["ari"], 3), f"{d['env_steps']:,}", f"{d['training_minutes']:.1f}", str(d["report"]["episodes_per_pair"]),
        ])  # fmt: skip
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
    "stream": stream,
    "features": features,
    "distances": distances,
    "assign": assign,
    "ablate": ablate,
}
