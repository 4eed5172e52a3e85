"""``covers-dist bench explore``: how often exploration noise finds a Meta-World task's success by chance.

Before a policy has learned a task its episodes are its mean plus noise, and a task whose success
lies off the mean's path is only learned once the noise finds it. This benchmark stands for such
an early policy with a fixed one that drives the hand straight at the task's object in the table
plane (``gain * (object - hand)`` in x and y, clipped to the action box; z and the gripper 0), the
path a policy takes once it has learned to approach the object; Button Press's button housing
stands in that path. Each setting adds Gaussian noise of standard deviation ``std`` to every
action entry, white (drawn afresh per step) or coloured (``ppo.noise_beta``: every step still
N(0, std), correlated along the episode, :mod:`covers_dist.ppo.noise`), and counts the episodes
that succeed at any step. Every setting runs the same initial states (``--episodes`` spread over
the group's transforms, one reset seed each) in one process; the ratio is to white noise of the
same ``std`` in the same run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from typing import Any

import numpy as np
import torch

from ..commands._common import CommaList
from ..config import ConfigError, load_config
from ..envs import make_task, suite_layout, task_names
from ..evaluation.stats import wilson_interval
from ..ppo.noise import NOISE_ENTRIES, coloured_entries, coloured_noise
from ..symmetry import get_group


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "explore", help="chance successes of a straight-at-the-object controller under white vs coloured action noise"
    )
    p.add_argument("--task", default="button-press-topdown-v3", help="Meta-World base task (default: button press)")
    p.add_argument("--betas", action=CommaList, default=["0", "1", "2"], metavar="B[,B...]",
                   help="noise colours, 0 = white (the baseline), 1 = pink, 2 = red (default: 0,1,2)")  # fmt: skip
    p.add_argument("--stds", action=CommaList, default=["1.0", "0.5"], metavar="S[,S...]",
                   help="noise standard deviations (default: 1.0,0.5)")  # fmt: skip
    p.add_argument("--entries", choices=NOISE_ENTRIES, default="all",
                   help="the action entries that get the colour, the others white (ppo.noise_entries; default: all)")  # fmt: skip
    p.add_argument("--episodes", type=int, default=64, help="episodes per setting, over the transforms (default: 64)")
    p.add_argument("--steps", type=int, default=150, help="episode length in env steps (default: 150)")
    p.add_argument("--gain", type=float, default=10.0, help="controller gain per metre (default: 10)")
    p.add_argument("--group", default="D4", help="the transforms the episodes cycle through (default: D4)")
    p.add_argument("--seed", type=int, default=0, help="reset seeds start here; the noise generator's seed")
    p.add_argument("--json", action="store_true", help="print one JSON object per setting")
    p.set_defaults(func=run)


def _floats(values: list[str], name: str, low: float, high: float) -> list[float]:
    out = []
    for v in values:
        try:
            x = float(v)
        except ValueError:
            raise SystemExit(f"covers-dist bench explore: {name} needs numbers, got {v!r}") from None
        if not low <= x <= high:
            raise SystemExit(f"covers-dist bench explore: {name} values must lie in [{low}, {high}], got {x}")
        out.append(x)
    return out


def run_setting(envs: list[Any], seeds: list[int], beta: float, std: float, steps: int, gain: float,
                seed: int, coloured: list[bool] | None = None) -> dict[str, Any]:  # fmt: skip
    """One setting's episodes (``envs[i]`` reset with ``seeds[i]``); successes, first-success steps
    and how far the hand rose above its start. ``coloured``: the entries that get the colour
    (:func:`covers_dist.ppo.noise.coloured_entries`; None: all)."""
    gen = torch.Generator().manual_seed(seed)
    successes, first, rise = 0, [], []
    for env, reset_seed in zip(envs, seeds):
        env.reset(seed=reset_seed)
        noise = coloured_noise(beta, steps, env.action_space.shape[0], gen, coloured).numpy()
        z0 = env.task_state()["hand"][2]
        top, hit = z0, None
        for t in range(steps):
            state = env.task_state()
            mean = np.zeros(env.action_space.shape[0])
            mean[:2] = np.clip(gain * (state["object"][:2] - state["hand"][:2]), -1.0, 1.0)
            _, _, term, trunc, info = env.step(np.clip(mean + std * noise[t], -1.0, 1.0).astype(np.float32))
            top = max(top, env.task_state()["hand"][2])
            if hit is None and info.get("success", 0.0) > 0:
                hit = t + 1
            if term or trunc:
                break
        successes += hit is not None
        first += [hit] if hit is not None else []
        rise.append(top - z0)
    n = len(envs)
    low, high = wilson_interval(successes, n)
    return {
        "beta": beta,
        "std": std,
        "episodes": n,
        "successes": successes,
        "success_rate": round(successes / n, 4),
        "ci95": [round(low, 4), round(high, 4)],
        "first_success_step_median": statistics.median(first) if first else None,
        "hand_rise_m_median": round(float(np.median(rise)), 4),
    }


def run(args: argparse.Namespace) -> int:
    prog = "covers-dist bench explore"
    if args.task not in task_names("metaworld"):
        raise SystemExit(f"{prog}: unknown Meta-World task {args.task!r}; valid: {', '.join(task_names('metaworld'))}")
    if args.episodes < 1 or args.steps < 1:
        raise SystemExit(f"{prog}: --episodes and --steps must be >= 1")
    betas = _floats(args.betas, "--betas", 0.0, 2.0)
    stds = _floats(args.stds, "--stds", 1e-6, 10.0)
    if 0.0 not in betas:
        betas = [0.0, *betas]  # white noise is the baseline of every ratio
    try:
        cfg = load_config("quickstart", [f"env.max_episode_steps={args.steps}", f"env.group={args.group}"])
        elements = [g.name for g in get_group(cfg.env.group)]
    except (ConfigError, ValueError, KeyError) as exc:
        raise SystemExit(f"{prog}: {exc}") from None
    layout = suite_layout(cfg.env.suite, cfg.env.image_size)
    coloured = coloured_entries(args.entries, layout.action_dim, layout.action_pairs)
    env_cfg = dataclasses.replace(cfg.env, success_bonus=0.0)
    envs: dict[str, Any] = {g: make_task(env_cfg, args.task, g) for g in elements}
    order = [elements[i % len(elements)] for i in range(args.episodes)]
    seeds = [args.seed + i for i in range(args.episodes)]
    rows = []
    total = len(betas) * len(stds)
    t_start = time.perf_counter()
    for std in stds:
        white = None
        for beta in sorted(betas):
            row = run_setting([envs[g] for g in order], seeds, beta, std, args.steps, args.gain, args.seed, coloured)
            row["task"] = args.task
            row["entries"] = args.entries
            if beta == 0.0:
                white = row["success_rate"]
            row["vs_white"] = None if not white else round(row["success_rate"] / white, 2)
            rows.append(row)
            done = len(rows)
            elapsed = time.perf_counter() - t_start
            print(f"[{done}/{total}] std {std} beta {beta}: {elapsed:.0f} s, ETA {elapsed / done * (total - done):.0f} s",
                  file=sys.stderr)  # fmt: skip
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                first = row["first_success_step_median"]
                ratio = "n/a (white found none)" if row["vs_white"] is None else f"{row['vs_white']:.2f}x white"
                print(
                    f"{args.task} std {std:.2f} beta {beta:.1f} ({args.entries}): "
                    f"{row['successes']}/{row['episodes']} succeed "
                    f"({row['success_rate']:.3f}, 95% CI {row['ci95'][0]:.3f}-{row['ci95'][1]:.3f}; {ratio}), "
                    f"first success at step {first if first is not None else '-'} (median), "
                    f"hand rises {row['hand_rise_m_median']:.3f} m (median)",
                    flush=True,
                )
    for env in envs.values():
        env.close()
    return 0
