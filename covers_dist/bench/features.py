"""``covers-dist bench features``: how well each feature source tells the task groups apart, as the
encoders train.

For each checkpoint given (a run's ``checkpoints/ckpt-*`` directories, or copies of them taken
during a run), the bank and every policy's weights are loaded read-only and held-out initial
frames are rendered for every group of the run (``--batches`` batches of ``--batch`` episodes
each, spread over the group's elements; reset seeds of their own, never those of training or
evaluation). Each candidate feature source then serves the checkpoint's bank in turn:

* ``own``: each policy's own current encoder (the paper's choice);
* ``joint``: every policy's unit-length invariant features side by side
  (:class:`~covers_dist.clustering.joint.JointFeatures`);
* ``fresh``: one untrained encoder (``feature_source: shared``);
* ``colors``: the colour histogram (no network).

Per (checkpoint, candidate) it prints, over the policies that trained on one group (the group
most of their episodes came from):

* ``separation``: the smallest, over policies ``i``, of median W1(other group's batch, B_i) /
  median W1(own group's batch, B_i) (the bank's metric and feature normalization); the two
  medians themselves per policy (``same_group_distance``, ``nearest_other_distance``, in the
  bank's units: W1 over the buffer's spread);
* ``correct``: the fraction of held-out batches the bank's rule (as configured: calibrated or
  threshold) recalls to a policy of their own group, ``new`` the fraction it would give a new
  policy, ``wrong`` the fraction it recalls to another group's policy.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

CANDIDATES: tuple[str, ...] = ("own", "joint", "fresh", "colors")
_SEED_TAG = 0xFEA7  # held-out frames: never a training (SeedSequence([seed, episode])) or evaluation seed


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("features", help="group separation and assignment accuracy of each feature source, per checkpoint")
    p.add_argument("checkpoints", nargs="+", help="checkpoint directories (RUN/checkpoints/ckpt-*) or run directories")
    p.add_argument("--candidates", default=",".join(CANDIDATES), help=f"comma-separated of {list(CANDIDATES)}")
    p.add_argument("--batch", type=int, default=8, help="episodes (first frames) per held-out batch (default: 8)")
    p.add_argument("--batches", type=int, default=8, help="held-out batches per group (default: 8)")
    p.add_argument("--seed", type=int, default=0, help="seed of the held-out frames (default: 0)")
    p.add_argument("--palette", default=None, help="render the frames with this env.palette (default: the run's)")
    p.add_argument("--json", action="store_true", help="print one JSON object per (checkpoint, candidate)")
    p.set_defaults(func=run)


def _checkpoint_dirs(paths: list[str]) -> list[tuple[Path, Path]]:
    """(run directory, checkpoint directory) for each path: a checkpoint, or a run (its newest)."""
    from ..runtime.checkpoint import latest_valid_checkpoint

    out = []
    for raw in paths:
        path = Path(raw)
        if (path / "learners").is_dir():
            run_dir = path.parent.parent if path.parent.name == "checkpoints" else path.parent
            if not (run_dir / "config.yaml").is_file() and (path / "config.yaml").is_file():
                run_dir = path
            out.append((run_dir, path))
        elif (path / "config.yaml").is_file():
            ckpt = latest_valid_checkpoint(path, log=lambda _m: None)
            if ckpt is None:
                raise SystemExit(f"covers-dist bench features: {path} has no valid checkpoint")
            out.append((path, ckpt))
        else:
            raise SystemExit(f"covers-dist bench features: {path} is neither a checkpoint nor a run directory")
    return out


def held_out_frames(cfg: Any, batch: int, batches: int, seed: int, palette: str | None = None) -> dict[int, list[dict]]:
    """``{group id: [obs batch, ...]}``: first frames of fresh episodes of every task of ``cfg``,
    batch ``b`` of a group on element ``b mod |G|``."""
    from dataclasses import replace

    from ..envs import make_task
    from ..symmetry import get_group

    env_cfg = cfg.env if palette is None else replace(cfg.env, palette=palette)
    elements = list(get_group(cfg.env.group))
    out: dict[int, list[dict]] = {}
    for gid, task in enumerate(cfg.env.tasks):
        envs = [make_task(env_cfg, task, g) for g in elements[: min(batches, len(elements))]]
        out[gid] = []
        for b in range(batches):
            env = envs[b % len(elements)]
            frames = []
            for i in range(batch):
                s = int(np.random.SeedSequence([seed, _SEED_TAG, gid, b, i]).generate_state(1)[0])
                frames.append(env.reset(seed=s)[0])
            out[gid].append({k: np.stack([f[k] for f in frames]) for k in ("image", "proprio")})
        for env in envs:
            env.close()
    return out


def candidate_fn(name: str, saved: Any) -> Any:
    """The feature function of candidate ``name`` for a loaded checkpoint ``saved``."""
    import torch

    from ..clustering.features import SharedFeatures, color_histogram
    from ..clustering.joint import JointFeatures
    from ..envs import suite_layout
    from ..models import build_actor_critic
    from ..runtime.learner import policy_seed

    service = saved.service
    if name == "own":
        return service._own_features
    if name == "joint":
        return JointFeatures(lambda: {pid: (0, m.features_np) for pid, m in service.models.items()})
    if name == "fresh":
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(policy_seed(saved.cfg.seed, 0))
            model = build_actor_critic(saved.cfg.network, suite_layout(saved.cfg.env.suite, saved.cfg.env.image_size))
        return SharedFeatures(model.eval().features_np)
    if name == "colors":
        return SharedFeatures(color_histogram)
    raise SystemExit(f"covers-dist bench features: unknown candidate {name!r}; expected some of {list(CANDIDATES)}")


def measure(saved: Any, frames: dict[int, list[dict]], candidate: str) -> dict[str, Any]:
    """Separation and assignment accuracy of ``candidate`` on the bank of ``saved`` (see module doc)."""
    bank = saved.service.bank
    majority = {
        pid: max(e.group_counts, key=lambda g: (e.group_counts[g], -g)) for pid, e in bank.entries.items() if e.group_counts
    }
    bank.set_feature_fn(candidate_fn(candidate, saved))
    t0 = time.perf_counter()
    d: dict[tuple[int, int], list[float]] = {}
    counts = {"correct": 0, "new": 0, "wrong": 0}
    for gid, batches in frames.items():
        for obs in batches:
            for pid, v in bank.distances(obs).items():
                d.setdefault((pid, gid), []).append(v)
            rec = bank.what_if(obs)
            if rec.decision == "new":
                counts["new"] += 1
            elif majority.get(rec.policy_id) == gid:
                counts["correct"] += 1
            else:
                counts["wrong"] += 1
    ratios, same_d, other_d = {}, {}, {}
    for pid, own_group in majority.items():
        same = statistics.median(d[(pid, own_group)]) if (pid, own_group) in d else None
        others = [statistics.median(d[(pid, g)]) for g in frames if g != own_group and (pid, g) in d]
        if same and others:
            ratios[pid] = min(others) / same
            same_d[pid], other_d[pid] = same, min(others)
    total = sum(counts.values())
    return {
        "candidate": candidate,
        "policies": len(bank),
        "policy_groups": {str(k): v for k, v in sorted(majority.items())},
        "separation": min(ratios.values()) if ratios else None,
        "separation_per_policy": {str(k): round(v, 3) for k, v in sorted(ratios.items())},
        "same_group_distance": {str(k): round(v, 3) for k, v in sorted(same_d.items())},
        "nearest_other_distance": {str(k): round(v, 3) for k, v in sorted(other_d.items())},
        **{k: v / max(total, 1) for k, v in counts.items()},
        "batches": total,
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def run(args: Any) -> int:
    from ..runtime.saved_run import load_checkpoint

    candidates = [c.strip() for c in args.candidates.split(",") if c.strip()]
    bad = [c for c in candidates if c not in CANDIDATES]
    if bad or not candidates:
        raise SystemExit(f"covers-dist bench features: unknown candidate(s) {bad}; expected some of {list(CANDIDATES)}")
    if args.batch < 1 or args.batches < 1:
        raise SystemExit("covers-dist bench features: --batch and --batches must be >= 1")
    frames = None
    for run_dir, ckpt in _checkpoint_dirs(args.checkpoints):
        saved = load_checkpoint(run_dir, ckpt, log=lambda _m: None)
        if frames is None:
            frames = held_out_frames(saved.cfg, args.batch, args.batches, args.seed, args.palette)
        steps = int(saved.driver.get("env_steps", 0))
        for name in candidates:
            row = {"checkpoint": ckpt.name, "env_steps": steps, **measure(saved, frames, name)}
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                sep = "n/a" if row["separation"] is None else f"{row['separation']:.2f}x"
                print(
                    f"{ckpt.name} {steps:>8} env steps {name:>6}: {row['policies']} policies, separation {sep}, "
                    f"correct {row['correct']:.2f} new {row['new']:.2f} wrong {row['wrong']:.2f} "
                    f"({row['batches']} batches, {row['wall_s']} s)",
                    flush=True,
                )
    return 0
