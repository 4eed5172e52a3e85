"""Stream results as committed files, and the tables of docs/RESULTS.md from them.

    python scripts/stream_results.py summarize RUN_DIR --role report --out docs/results/stream/NAME.json
    python scripts/stream_results.py table docs/results/stream/*.json

``summarize`` reads a finished run directory (config.yaml, metrics.jsonl, eval.jsonl, the newest
checkpoint's bank) and writes one JSON file: the config and seed, whether the seed was used to
choose settings (``--role tuning``) or only to report (``--role report``), the CPU of the machine
that ran it (this machine: summarize where the run ran), env steps, training minutes (the sum of
the iterations' wall-clock, resumes included, pauses between them not), policies (at the end and
ever created), ARI, and per group the greedy success of the newest ``report``-split pass of
``covers-dist eval`` (mean and worst over the trainable copies, and the held-out copies), with
the episodes per copy. ``table`` prints one markdown row per file.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import yaml

GAP_S = 120.0  # metrics rows further apart than this are a pause (a stop and a resume), not training


def cpu_model() -> str:
    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    fields = dict(line.split(":", 1) for line in info.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    flags = fields.get("flags", "").split()
    isa = "AVX-512" if "avx512f" in flags else ("AVX2" if "avx2" in flags else "no AVX2")
    return f"{fields.get('model name', 'unknown')} (family {fields.get('cpu family', '?')} model {fields.get('model', '?')}, {isa})"


def lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


def training_minutes(rows: list[dict[str, Any]]) -> float:
    times = [r["wall_time"] for r in rows if "wall_time" in r]
    return sum(b - a for a, b in zip(times, times[1:]) if 0 <= b - a < GAP_S) / 60.0


def group_results(ev: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for r in ev["pairs"]:
        res = r["results"].get("greedy/agnostic")
        if res is None:
            continue
        g = out.setdefault(r["task"], {"trainable": [], "held_out": []})
        g["held_out" if r["status"] == "held_out" else "trainable"].append(
            {"g": r["g"], "success": res["success"], "n": res["n"], "policies": res.get("policies", [res["policy_id"]])}
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


def summarize(run_dir: Path, role: str, label: str | None) -> dict[str, Any]:
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    rows = lines(run_dir / "metrics.jsonl")
    last = rows[-1]
    passes = [p for p in lines(run_dir / "eval.jsonl") if p.get("split") == "report"]
    if not passes:
        raise SystemExit(f"{run_dir}: no report-split pass in eval.jsonl; run `covers-dist eval {run_dir} --episodes 16` first")
    ev = passes[-1]
    ckpts = sorted((run_dir / "checkpoints").glob("ckpt-*"))
    bank = json.loads((ckpts[-1] / "bank" / "bank.json").read_text()) if ckpts else {}
    state = bank.get("state", bank)
    created = len(state.get("entries", [])) + len(state.get("retired", []))
    stop_passes = [p for p in lines(run_dir / "eval.jsonl") if p.get("split") == "stop"]
    return {
        "label": label or cfg.get("name"),
        "config": cfg.get("name"),
        "method": cfg["runtime"]["method"],
        "seed": cfg["seed"],
        "role": role,
        "feature_source": cfg["clustering"]["feature_source"],
        "palette": cfg["env"].get("palette", "task"),
        "cpu": cpu_model(),
        "env_steps": last["env_steps"],
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
        "stop_passes": len(stop_passes),
    }


def f(v: Any, digits: int = 2) -> str:
    return "n/a" if v is None else f"{float(v):.{digits}f}"


def table(paths: list[str]) -> None:
    data = [json.loads(Path(p).read_text()) for p in paths]
    tasks = list(dict.fromkeys(t for d in data for t in d["report"]["groups"]))
    head = " | ".join(f"{t} (mean / worst / held-out)" for t in tasks)
    print(f"| run | seed (role) | {head} | policies (created) | ARI | env steps | minutes | CPU |")
    print("|---|---|" + "---|" * len(tasks) + "---|---|---|---|---|")
    for d in data:
        cells = []
        for t in tasks:
            g = d["report"]["groups"].get(t)
            cells.append("" if g is None else f"{f(g['mean'])} / {f(g['worst'])} / {f(g['held_out_worst'])}")
        print(
            f"| {d['label']} | {d['seed']} ({d['role']}) | " + " | ".join(cells) + f" | {d['policies']} ({d['policies_created']}) | "
            f"{f(d['ari'], 3)} | {d['env_steps']:,} | {d['training_minutes']:.1f} | {d['cpu']} |"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("summarize")
    s.add_argument("run_dir", type=Path)
    s.add_argument("--role", choices=("tuning", "report"), required=True)
    s.add_argument("--label")
    s.add_argument("--out", type=Path, required=True)
    t = sub.add_parser("table")
    t.add_argument("files", nargs="+")
    args = p.parse_args()
    if args.cmd == "summarize":
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summarize(args.run_dir, args.role, args.label), indent=1) + "\n")
        print(f"wrote {args.out}")
    else:
        table(args.files)


if __name__ == "__main__":
    main()
