"""``covers-dist bench toy``: steps/s of each toy task on one core."""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from ..envs.toy import TOY_TASKS, ToyTask

TARGET_STEPS_PER_S = 2000.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("toy", help="toy task steps/s per task (target >= 2,000 on one core)")
    p.add_argument("--steps", type=int, default=5000, help="steps per repeat (default: 5000)")
    p.add_argument("--repeats", type=int, default=3, help="repeats; the median is reported (default: 3)")
    p.add_argument("--image-size", type=int, default=32, help="image side (default: 32)")
    p.add_argument("--json", action="store_true", help="print one JSON object per task")
    p.set_defaults(func=run)


def measure(task: str, steps: int, repeats: int, image_size: int, seed: int = 0) -> float:
    env = ToyTask(task, "r3f", image_size=image_size)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, size=(steps, 2)).astype(np.float32)
    rates = []
    for _ in range(repeats):
        env.reset(seed=seed)
        t0 = time.perf_counter()
        for a in actions:
            _, _, _, trunc, _ = env.step(a)
            if trunc:
                env.reset()
        rates.append(steps / (time.perf_counter() - t0))
    return statistics.median(rates)


def run(args: argparse.Namespace) -> int:
    if args.steps < 1 or args.repeats < 1:
        raise SystemExit("covers-dist bench toy: --steps and --repeats must be >= 1")
    ok = True
    for task in TOY_TASKS:
        rate = measure(task, args.steps, args.repeats, args.image_size)
        row = {
            "task": task,
            "image_size": args.image_size,
            "steps_per_s": round(rate, 1),
            "target_steps_per_s": TARGET_STEPS_PER_S,
            "ratio_to_target": round(rate / TARGET_STEPS_PER_S, 2),
        }
        ok &= rate >= TARGET_STEPS_PER_S
        print(json.dumps(row) if args.json else f"{task:6s} {args.image_size}px  {rate:9,.0f} steps/s  ({rate / TARGET_STEPS_PER_S:.1f}x target)")
    return 0
