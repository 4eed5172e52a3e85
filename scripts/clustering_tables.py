"""Markdown tables of docs/clustering.md and docs/RESULTS.md from the committed result files.

    python scripts/clustering_tables.py features FILE.jsonl   # `covers-dist bench features --json` output
    python scripts/clustering_tables.py distances FILE.jsonl  # the same, W1 within and between groups
    python scripts/clustering_tables.py assign FILE.jsonl...  # `covers-dist bench assign --stream --json`
    python scripts/clustering_tables.py ablate FILE.jsonl...  # `covers-dist bench ablate --json` (cell rows)

Each prints one table to stdout; the docs hold these tables as printed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def rows(paths: list[str]) -> list[dict]:
    out = []
    for p in paths:
        out += [json.loads(line) for line in Path(p).read_text().splitlines() if line.strip()]
    return out


def f(v, digits: int = 2) -> str:
    return "n/a" if v is None else f"{float(v):.{digits}f}"


def features(paths: list[str]) -> None:
    data = rows(paths)
    candidates = list(dict.fromkeys(r["candidate"] for r in data))
    print("| env steps | " + " | ".join(f"{c}: separation / correct" for c in candidates) + " |")
    print("|---|" + "---|" * len(candidates))
    for steps in sorted({r["env_steps"] for r in data}):
        cells = []
        for c in candidates:
            r = next((r for r in data if r["env_steps"] == steps and r["candidate"] == c), None)
            cells.append("" if r is None else f"{f(r['separation'], 1)}x / {f(r['correct'])}")
        print(f"| {steps:,} | " + " | ".join(cells) + " |")


def distances(paths: list[str]) -> None:
    print("| env steps | features | same group: median W1 per policy (min-max) | nearest other group (min-max) |")
    print("|---|---|---|---|")
    for r in sorted(rows(paths), key=lambda r: (r["env_steps"], r["candidate"])):
        same, other = list(r["same_group_distance"].values()), list(r["nearest_other_distance"].values())
        print(f"| {r['env_steps']:,} | {r['candidate']} | {f(min(same))}-{f(max(same))} | {f(min(other))}-{f(max(other))} |")


def assign(paths: list[str]) -> None:
    print("| stream | features | seed | env steps | policies (created) | true groups | merges | ARI | wrong-policy episodes | wall s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows(paths):
        print(
            f"| {r['stream']} | {r['feature_source']} | {r['seed']} | {r['env_steps']:,} | {r['policies']} "
            f"({r.get('policies_created', r['policies'])}) | {r['true_groups']} | {r.get('merges', 0)} | {f(r['ari'], 3)} | "
            f"{f(r['wrong_policy_fraction'], 3)} | {r['wall_s']:.0f} |"
        )


def ablate(paths: list[str]) -> None:
    print("| cell | seeds | policies created | false splits | merges | ARI (mean / min) | wrong-policy episodes |")
    print("|---|---|---|---|---|---|---|")
    for r in rows(paths):
        if "seeds" not in r:  # a run row; the cell rows follow them
            continue
        print(
            f"| {r['cell']} | {','.join(map(str, r['seeds']))} | {f(r['policies_created'], 1)} | {f(r['false_splits'], 1)} | "
            f"{f(r['merges'], 1)} | {f(r['ari'], 3)} / {f(r['ari_min'], 3)} | {f(r['wrong_policy_fraction'], 3)} |"
        )


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("features", "distances", "assign", "ablate"):
        sys.exit(__doc__)
    {"features": features, "distances": distances, "assign": assign, "ablate": ablate}[sys.argv[1]](sys.argv[2:])
