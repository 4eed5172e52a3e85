"""``covers-dist demo``: roll out every toy task under every symmetry and write an image grid.

This is what the project can show without training: each toy task group, seen through each
element of D4, stepped with random actions that are transformed with the task, while checking
that the transformed task is exactly equivalent to the base task (pixel-equal images, equal
rewards). It writes ``toy_grid.png`` (rows: task groups, columns: D4 elements) into the output
directory (default ``runs/toy-grid``) and prints the measured steps/s. It trains nothing; ``make
demo`` is the training demo (``runs/demo``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from ..envs.toy import TOY_TASKS, ToyTask
from ..symmetry import D4_ELEMENTS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="roll out the toy tasks under all of D4 and write an image grid (no training; `make demo` trains)"
    )
    p.add_argument("--out", default="runs/toy-grid", help="output directory (default: runs/toy-grid)")
    p.add_argument("--episodes", type=int, default=2, help="episodes per (task, element) (default: 2)")
    p.add_argument("--image-size", type=int, default=64, help="image side in pixels (default: 64)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from PIL import Image

    if args.episodes < 1:
        raise SystemExit("covers-dist demo: --episodes must be >= 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    rows, steps, mismatches = [], 0, 0
    t0 = time.perf_counter()
    for task in TOY_TASKS:
        row = []
        for g in D4_ELEMENTS:
            base = ToyTask(task, "e", image_size=args.image_size)
            env = ToyTask(task, g, image_size=args.image_size)
            for ep in range(args.episodes):
                seed = int(rng.integers(2**31))
                ob, _ = base.reset(seed=seed)
                og, _ = env.reset(seed=seed)
                if ep == 0:
                    row.append(og["image"])
                done = False
                while not done:
                    a = rng.uniform(-1, 1, size=2).astype(np.float32)
                    ob, rb, _, done, _ = base.step(a)
                    og, rg, _, _, _ = env.step(g.apply_vectors(a))
                    steps += 1
                    if rb != rg or not np.array_equal(g.apply_image(ob["image"]), og["image"]):
                        mismatches += 1
        rows.append(np.concatenate([np.pad(im, ((2, 2), (2, 2), (0, 0)), constant_values=255) for im in row], 1))
    elapsed = time.perf_counter() - t0
    grid = np.concatenate(rows, 0)
    path = out / "toy_grid.png"
    Image.fromarray(grid).resize((grid.shape[1] * 2, grid.shape[0] * 2), Image.NEAREST).save(path)
    print(f"toy tasks {list(TOY_TASKS)} x D4 elements {[g.name for g in D4_ELEMENTS]}")
    print(f"{steps} paired steps in {elapsed:.2f} s ({2 * steps / elapsed:,.0f} env steps/s incl. checks)")
    print(f"equivalence mismatches (image or reward): {mismatches}")
    print(f"wrote {path} (rows: task groups, columns: D4 elements at their first reset)")
    return 0 if mismatches == 0 else 1
