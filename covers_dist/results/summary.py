"""A finished run as one small result file: what the results tables are made of.

:func:`summarize` reads a run directory (``config.yaml``, ``metrics.jsonl``, ``eval.jsonl``, the
newest checkpoint's bank, ``provenance.jsonl``) and returns a JSON-able dict: the config and seed,
whether the seed chose settings (``role="tuning"``) or only reports (``"report"``), the commit
and CPU, env steps, training minutes, policies, ARI and, per group, the greedy success of the
newest ``report``-split pass of ``covers-dist eval`` with every (task, g)'s successes and ``n``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml

from .provenance import cpu_model, read_starts

ROLES = ("tuning", "report")
SCHEMA = "covers-dist/run-result/1"
GAP_S = 120.0  # metrics rows further apart than this are a pause (a stop and a resume), not training


class ResultError(ValueError):
    """A run directory or result file cannot give the result asked for."""


def _lines(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        raise ResultError(f"{path}: missing (is {path.parent} a run directory?)")
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


def training_minutes(rows: list[dict[str, Any]]) -> float:
    """The iterations' wall-clock summed, resumes included, the pauses between them not."""
    times = [r["wall_time"] for r in rows if "wall_time" in r]
    return sum(b - a for a, b in zip(times, times[1:]) if 0 <= b - a < GAP_S) / 60.0


def group_results(ev: dict[str, Any], key: str = "greedy/agnostic") -> dict[str, Any]:
    """Per task of a pass: mean and worst success over its trainable copies and its held-out
    copies, and each copy's ``g``, ``success``, ``successes``, ``n`` and acting policies."""
    out: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for r in ev["pairs"]:
        res = r["results"].get(key)
        if res is None:
            continue
        g = out.setdefault(r["task"], {"trainable": [], "held_out": []})
        g["held_out" if r["status"] == "held_out" else "trainable"].append(
            {
                "g": r["g"],
                "success": res["success"],
                "successes": res.get("successes"),
                "n": res["n"],
                "policies": sorted(set(res.get("policies", [res["policy_id"]]))),
            }
        )
    summary = {}
    for task, g in out.items():
        tr, ho = [p["success"] for p in g["trainable"]], [p["success"] for p in g["held_out"]]
        summary[task] = {
            "mean": sum(tr) / len(tr) if tr else None,
            "worst": min(tr) if tr else None,
            "held_out_mean": sum(ho) / len(ho) if ho else None,
            "held_out_worst": min(ho) if ho else None,
            "pairs": g,
        }
    return summary


def stop_reason(cfg: dict[str, Any], rows: list[dict[str, Any]], passes: list[dict[str, Any]]) -> str:
    """Why training ended: ``budget`` (the env-step budget), ``held`` (every evaluated pair at
    ``eval.stop_at`` on the last ``eval.held`` stop passes), ``time limit``, or ``other``."""
    steps, minutes = rows[-1]["env_steps"], training_minutes(rows)
    if steps >= cfg["runtime"]["total_env_steps"]:
        return "budget"
    ev = cfg.get("eval", {})
    stop_at, held = ev.get("stop_at"), int(ev.get("held", 2) or 2)
    stops = [p for p in passes if p.get("split") == "stop"]
    if stop_at is not None and len(stops) >= held:
        def ok(p: dict[str, Any]) -> bool:
            got = [r["results"].get("greedy/agnostic") for r in p["pairs"] if r["status"] != "held_out"]
            return bool(got) and all(g is not None and g["success"] >= stop_at for g in got)

        if all(ok(p) for p in stops[-held:]) and stops[-1]["env_steps"] >= steps - 1:
            return "held"
    limit = cfg["runtime"].get("time_limit_minutes")
    if limit and minutes >= 0.98 * limit:
        return "time limit"
    return "other"


def summarize(run_dir: str | Path, role: str, label: str | None = None, commit: str | None = None) -> dict[str, Any]:
    """The result file of the run in ``run_dir`` (see the module doc)."""
    run_dir = Path(run_dir)
    if role not in ROLES:
        raise ResultError(f"role must be one of {ROLES}, got {role!r}")
    if not (run_dir / "config.yaml").exists():
        raise ResultError(f"{run_dir}: no config.yaml (not a run directory)")
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    rows = _lines(run_dir / "metrics.jsonl")
    if not rows:
        raise ResultError(f"{run_dir}/metrics.jsonl: no iterations")
    passes = _lines(run_dir / "eval.jsonl") if (run_dir / "eval.jsonl").exists() else []
    report = [p for p in passes if p.get("split") == "report"]
    if not report:
        raise ResultError(f"{run_dir}: no report-split pass in eval.jsonl; run `covers-dist eval {run_dir} --episodes 16` first")
    ev = report[-1]
    starts = read_starts(run_dir)
    commits = sorted({s["commit"] for s in starts if s.get("commit")})
    if commit is None:
        if len(commits) != 1:
            raise ResultError(
                f"{run_dir}: the code's commit is {'unknown' if not commits else 'ambiguous ' + str(commits)} "
                "(provenance.jsonl); pass it with --commit"
            )
        commit = commits[0]
    ckpts = sorted((run_dir / "checkpoints").glob("ckpt-*"))
    bank = json.loads((ckpts[-1] / "bank" / "bank.json").read_text()) if ckpts else {}
    state = bank.get("state", bank)
    created = len(state.get("entries", [])) + len(state.get("retired", []))
    last = rows[-1]
    return {
        "schema": SCHEMA,
        "label": label or cfg.get("name"),
        "config": cfg.get("name"),
        "method": cfg["runtime"]["method"],
        "seed": cfg["seed"],
        "role": role,
        "commit": commit,
        "suite": cfg["env"]["suite"],
        "tasks": list(cfg["env"]["tasks"]),
        "group": cfg["env"]["group"],
        "feature_source": cfg["clustering"]["feature_source"],
        "palette": cfg["env"].get("palette", "task"),
        "cpu": next((s["cpu"] for s in starts if s.get("cpu")), None) or cpu_model(),
        "budget": {
            "env_steps": cfg["runtime"]["total_env_steps"],
            "minutes": cfg["runtime"].get("time_limit_minutes"),
        },
        "env_steps": last["env_steps"],
        "stopped": stop_reason(cfg, rows, passes),
        "training_minutes": round(training_minutes(rows), 1),
        "policies": last.get("num_policies"),
        "policies_created": created or last.get("num_policies"),
        "merges": len(state.get("merges", [])),
        "ari": last.get("ari"),
        "report": {
            "episodes_per_pair": ev["episodes_per_job"],
            "iteration": ev["iteration"],
            "episode_choice_disagreement": ev.get("episode_choice_disagreement"),
            "groups": group_results(ev),
        },
        "stop_passes": sum(1 for p in passes if p.get("split") == "stop"),
    }


def read_result(path: str | Path) -> dict[str, Any]:
    """A result file written from :func:`summarize` (or a JSON-lines file of rows, as a list)."""
    path = Path(path)
    text = path.read_text()
    if path.suffix == ".jsonl":
        return {"rows": [json.loads(x) for x in text.splitlines() if x.strip()]}
    return json.loads(text)
