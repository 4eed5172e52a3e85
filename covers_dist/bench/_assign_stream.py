"""``covers-dist bench assign --stream``: the assignment rule on streams with TRAINING encoders.

Runs the real COVERS loop (serial backend: the same rollout workers, clustering service and
learners as on Ray, in one process) on each stream for each decision rule
(``clustering.rule``) and assignment moment (``clustering.assign_at``), and reports:

* false splits per 1,000 assignments: policies created beyond one per true group (on a
  one-group stream every new policy is one);
* ARI between the policy id and the true group of every training episode;
* the fraction of episodes acted by a policy other than the one they were assigned to.

Streams: ``toy-one`` (toy reach alone under D4), ``toy-multi`` (reach, push, avoid),
``metaworld-one`` (Goal Reach alone under D4, 64 px), ``metaworld-multi`` (the four groups).
Each run trains for ``--steps`` env steps with ``clustering.update_every`` = ``--batch``
episodes per assignment, on top of the stream's config (the smoke config for toy streams, the
quickstart config for Meta-World ones; ``--config`` replaces it, ``--set`` adds overrides).
"""

from __future__ import annotations

import contextlib
import json
import sys
import tempfile
import time
from typing import Any

STREAMS: dict[str, tuple[str, list[str]]] = {
    "toy-one": ("configs/smoke.yaml", ["env.tasks=[reach]"]),
    "toy-multi": ("configs/smoke.yaml", ["env.tasks=[reach,push,avoid]"]),
    "metaworld-one": ("configs/quickstart.yaml", ["env.tasks=[reach-v3]"]),
    "metaworld-multi": (
        "configs/quickstart.yaml",
        ["env.tasks=[reach-v3,button-press-topdown-v3,drawer-close-v3,plate-slide-v3]"],
    ),
}


def run_stream(
    stream: str,
    rule: str,
    assign_at: str,
    steps: int,
    batch: int,
    seed: int,
    extra: list[str],
    config: str | None = None,
) -> dict:
    """One serial training run; the figures above as a dict (``config`` replaces the stream's base config)."""
    from ..config import load_config
    from ..runtime.driver import Trainer

    base, overrides = STREAMS[stream]
    config = config or base
    given = load_config(config, overrides + list(extra))
    minibatch = min(given.ppo.minibatch_size, batch * given.env.max_episode_steps)  # one update's samples
    with tempfile.TemporaryDirectory(prefix="covers-bench-assign-") as run_dir:
        cfg = load_config(
            config,
            overrides
            + [
                f"clustering.rule={rule}",
                f"clustering.assign_at={assign_at}",
                f"clustering.update_every={batch}",
                f"ppo.minibatch_size={minibatch}",
                f"runtime.total_env_steps={steps}",
                f"runtime.run_dir={run_dir}",
                "runtime.serial=true",
                "runtime.num_workers=1",
                f"runtime.envs_per_worker={min(batch, 8)}",
                f"runtime.checkpoint_every={10**6}",
                "runtime.log_every_s=60",
                f"seed={seed}",
                "eval.every_iterations=0",
            ]
            + list(extra),
        )
        t0 = time.perf_counter()
        trainer = Trainer(cfg, log=lambda _m: None)
        try:
            with contextlib.redirect_stdout(sys.stderr):  # the loop's progress lines; stdout is the bench's
                result = trainer.run()
            assignments = trainer.iteration
            row = result["row"]
        finally:
            trainer.close()
    policies = int(result["num_policies"])
    groups = len((result.get("confusion") or {}).get("groups", [])) or 1  # true groups the stream showed
    false_splits = max(policies - groups, 0)
    return {
        "stream": stream,
        "rule": rule,
        "assign_at": assign_at,
        "seed": seed,
        "env_steps": int(row.get("env_steps", 0)),
        "assignments": assignments,
        "policies": policies,
        "true_groups": groups,
        "false_splits": false_splits,
        "false_splits_per_1000": 1000.0 * false_splits / max(assignments, 1),
        "ari": result.get("ari"),
        "wrong_policy_fraction": row.get("wrong_policy_fraction"),
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def run(args: Any) -> int:
    rules = [r.strip() for r in args.rules.split(",") if r.strip()]
    modes = [m.strip() for m in args.assign_at.split(",") if m.strip()]
    streams = [s.strip() for s in args.streams.split(",") if s.strip()]
    bad = [s for s in streams if s not in STREAMS] + [r for r in rules if r not in ("threshold", "calibrated")]
    bad += [m for m in modes if m not in ("iteration", "reset")]
    if bad or not rules or not modes or not streams:
        raise SystemExit(
            f"covers-dist bench assign --stream: unknown or empty choice(s) {bad}; streams: {list(STREAMS)}, "
            "rules: threshold,calibrated, assign-at: iteration,reset"
        )
    if args.steps < 1 or args.batch < 1:
        raise SystemExit("covers-dist bench assign --stream: --steps and --batch must be >= 1")
    rows = []
    total = len(streams) * len(rules) * len(modes)
    for stream in streams:
        for rule in rules:
            for mode in modes:
                if not args.json:
                    print(f"[{len(rows) + 1}/{total}] {stream} rule={rule} assign_at={mode} ...", flush=True)
                row = run_stream(stream, rule, mode, args.steps, args.batch, args.seed, args.overrides, args.config)
                rows.append(row)
                if args.json:
                    print(json.dumps(row), flush=True)
                else:
                    print(
                        f"    {row['assignments']} assignments, {row['env_steps']} env steps, {row['wall_s']} s: "
                        f"policies {row['policies']} for {row['true_groups']} group(s), false splits "
                        f"{row['false_splits']} ({row['false_splits_per_1000']:.1f} per 1,000), ARI "
                        f"{_fmt(row['ari'])}, wrong-policy episodes {_fmt(row['wrong_policy_fraction'])}",
                        flush=True,
                    )
    return 0


def _fmt(v: Any) -> str:
    return "n/a" if v is None else f"{float(v):.3f}"
