"""``covers-dist bench assign --stream``: the assignment rule on streams with TRAINING encoders.

Runs the real COVERS loop (serial backend: the same rollout workers, clustering service and
learners as on Ray, in one process) on each stream for each decision rule
(``clustering.rule``) and assignment moment (``clustering.assign_at``), and reports:

* false splits per 1,000 assignments: policies created beyond one per true group (on a
  one-group stream every new policy is one), whether healing merged them later or not
  (``policies`` is the bank's size at the end, ``policies_created`` and ``merges`` beside it);
* ARI between the policy id and the true group of every training episode;
* the fraction of episodes acted by a policy other than the one they were assigned to.

Streams: ``toy-one`` (toy reach alone under D4), ``toy-multi`` (reach, push, avoid),
``metaworld-one`` (Goal Reach alone under D4, 64 px), ``metaworld-multi`` (the four groups),
``metaworld-mono`` (the four groups with ``env.palette: mono``: every object in one grey under a
flat light, so a colour histogram sees one picture and only learned features of shape and layout
can tell the groups apart). Each run trains for ``--steps`` env steps with
``clustering.update_every`` = ``--batch`` episodes per assignment, on top of the stream's config
(the smoke config for toy streams, the quickstart config for Meta-World ones; ``--config``
replaces it, ``--set`` adds overrides). Without ``--rules`` / ``--assign-at`` / ``--batch`` a
given ``--config`` keeps its own rule, moment and ``update_every``; without ``--steps`` a toy
stream runs 8,000 env steps and a Meta-World stream 16 of the config's segments
(``16 * env.episodes_per_task * env.max_episode_steps``: every group visited about 4 times).
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
    "metaworld-mono": (
        "configs/quickstart.yaml",
        ["env.tasks=[reach-v3,button-press-topdown-v3,drawer-close-v3,plate-slide-v3]", "env.palette=mono"],
    ),
}
TOY_STEPS = 8000
META_WORLD_SEGMENTS = 16
DEFAULT_BATCH = 4


def settings(stream: str, args: Any) -> tuple[list[str], list[str], int, int]:
    """(rules, assignment moments, env steps, batch) of ``stream`` for the parsed ``args`` (module doc)."""
    from ..config import load_config

    base, overrides = STREAMS[stream]
    cfg = load_config(args.config or base, overrides + list(args.overrides))
    given = args.config is not None

    def pick(value: str | None, own: str, both: str) -> list[str]:
        chosen = value if value is not None else (own if given else both)
        return [v.strip() for v in chosen.split(",") if v.strip()]

    rules = pick(args.rules, cfg.clustering.rule, "threshold,calibrated")
    modes = pick(args.assign_at, cfg.clustering.assign_at, "iteration,reset")
    batch = args.batch or (cfg.clustering.update_every if given else DEFAULT_BATCH)
    steps = args.steps or (
        TOY_STEPS if cfg.env.suite == "toy" else META_WORLD_SEGMENTS * cfg.env.episodes_per_task * cfg.env.max_episode_steps
    )
    return rules, modes, steps, batch


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
                "eval.stop_at=null",
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
            summary = trainer.backend.call_clustering("summary")
        finally:
            trainer.close()
    policies = int(result["num_policies"])
    created = int(summary.get("policies_created", policies))
    groups = len((result.get("confusion") or {}).get("groups", [])) or 1  # true groups the stream showed
    false_splits = max(created - groups, 0)  # every policy created beyond one per group, healed or not
    return {
        "stream": stream,
        "rule": rule,
        "assign_at": assign_at,
        "seed": seed,
        "feature_source": cfg.clustering.feature_source,
        "palette": cfg.env.palette,
        "env_steps": int(row.get("env_steps", 0)),
        "assignments": assignments,
        "policies": policies,
        "policies_created": created,
        "merges": len(summary.get("merges", [])),
        "true_groups": groups,
        "false_splits": false_splits,
        "false_splits_per_1000": 1000.0 * false_splits / max(assignments, 1),
        "ari": result.get("ari"),
        "wrong_policy_fraction": row.get("wrong_policy_fraction"),
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def run(args: Any) -> int:
    streams = [s.strip() for s in args.streams.split(",") if s.strip()]
    unknown = [s for s in streams if s not in STREAMS]
    if unknown or not streams:
        raise SystemExit(f"covers-dist bench assign --stream: unknown or empty stream(s) {unknown}; streams: {list(STREAMS)}")
    if args.steps < 0 or args.batch < 0:
        raise SystemExit("covers-dist bench assign --stream: --steps and --batch must be >= 1")
    plan = {stream: settings(stream, args) for stream in streams}
    for stream, (rules, modes, _, _) in plan.items():
        bad = [r for r in rules if r not in ("threshold", "calibrated")] + [m for m in modes if m not in ("iteration", "reset")]
        if bad or not rules or not modes:
            raise SystemExit(
                f"covers-dist bench assign --stream: unknown or empty choice(s) {bad}; "
                "rules: threshold,calibrated, assign-at: iteration,reset"
            )
    rows = []
    total = sum(len(r) * len(m) for r, m, _, _ in plan.values())
    for stream, (rules, modes, steps, batch) in plan.items():
        for rule in rules:
            for mode in modes:
                if not args.json:
                    print(f"[{len(rows) + 1}/{total}] {stream} rule={rule} assign_at={mode} ...", flush=True)
                row = run_stream(stream, rule, mode, steps, batch, args.seed, args.overrides, args.config)
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
