"""``covers-dist bench render``: Meta-World steps/s with and without rendering, in one process.

For each base task, measured in one run and interleaved (the machine is shared and noisy, so
the figures are medians over repeats and the ratios come from the same run):

* ``physics_steps_per_s``: Meta-World's own ``step`` alone (the base task, no image);
* ``rendered_steps_per_s``: a transformed task's full ``step`` (physics, the arm-free top-down
  image with this package's renderer, the group action on image, proprio and action);
* ``stock_rendered_steps_per_s``: Meta-World's ``step`` plus its stock ``topview`` camera through
  MuJoCo's GL renderer with fast settings (no shadows, reflections, skybox or multisampling).

Only ``step`` calls are timed (resets excluded, the same episodes for every mode). ``--policy``
picks random actions or Meta-World's scripted expert, which moves the objects (the renderer
redraws moving objects, so that is its slower case). ``--agreement`` compares the numpy
rasterizer with MuJoCo's GL camera of the same view, pixel for pixel; ``--grid PATH`` writes a
PNG of the base tasks under all eight elements of D4.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from typing import Any

import numpy as np

from ..commands._common import CommaList

DEFAULT_TASKS = ("reach-v3", "button-press-topdown-v3", "drawer-close-v3", "plate-slide-v3")
TARGET_RATIO = 0.5


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="Meta-World physics vs rendered steps/s (target: rendered >= 0.5 x physics)")
    p.add_argument("--tasks", action=CommaList, default=list(DEFAULT_TASKS), metavar="TASK[,TASK...]",
                   help="comma-separated base tasks (default: the four of the paper)")  # fmt: skip
    p.add_argument("--image-size", type=int, default=64, help="image side in pixels (default: 64)")
    p.add_argument("--steps", type=int, default=600, help="timed steps per mode and repeat (default: 600)")
    p.add_argument("--stock-steps", type=int, default=150, help="timed steps of the slow stock camera (default: 150)")
    p.add_argument("--repeats", type=int, default=3, help="repeats; medians are reported (default: 3)")
    p.add_argument("--policy", choices=("random", "expert", "both"), default="both", help="actions (default: both)")
    p.add_argument("--backend", default="numpy", choices=("numpy", "egl", "osmesa"), help="renderer (default: numpy)")
    p.add_argument("--no-stock", action="store_true", help="skip the stock GL camera")
    p.add_argument("--agreement", action="store_true", help="also compare the numpy image with MuJoCo's GL image")
    p.add_argument("--grid", metavar="PNG", help="write the D4 grid of the tasks to this PNG and exit")
    p.add_argument("--seed", type=int, default=0, help="seed of placements and actions (default: 0)")
    p.add_argument("--palette", choices=("task", "mono"), default="task", help="--grid: object colours (env.palette)")
    p.add_argument("--json", action="store_true", help="print one JSON object per task and policy")
    p.set_defaults(func=run)


def _next_action(env: Any, policy: str, rng: np.random.Generator) -> np.ndarray:
    if policy == "random":
        return rng.uniform(-1.0, 1.0, size=4).astype(np.float32)
    return env.expert_action()


def _time_episode(env: Any, mode: str, steps: int, policy: str, seed: int, stock: Any = None) -> float:
    """Seconds spent in ``steps`` step calls of one episode (reset with ``seed``, not timed)."""
    rng = np.random.default_rng(seed)
    mw = env.unwrapped_metaworld
    env.reset(seed=seed)
    elapsed = 0.0
    for _ in range(steps):
        a = _next_action(env, policy, rng)
        if mode == "rendered":
            t0 = time.perf_counter()
            env.step(a)
            elapsed += time.perf_counter() - t0
            continue
        base = env.layout.transform_action(env.g_inv, a)
        t0 = time.perf_counter()
        mw_obs = mw.step(base)[0]
        if stock is not None:
            stock.render()
        elapsed += time.perf_counter() - t0
        env._mw_obs = mw_obs  # keeps the scripted expert's view of the state current
    return elapsed


def measure_task(
    task: str,
    image_size: int,
    steps: int,
    stock_steps: int,
    repeats: int,
    policy: str,
    backend: str = "numpy",
    with_stock: bool = True,
    seed: int = 0,
) -> dict[str, Any]:
    """One row of the table: per repeat, the modes alternate episode by episode over the same
    episodes (same seeds, same actions); medians over ``repeats``."""
    from ..envs.metaworld_suite import MetaWorldTask

    env = MetaWorldTask(task, "r3f", image_size=image_size, render_backend=backend)
    stock = None
    if with_stock:
        from ..envs.gl_render import StockTopViewRenderer

        stock = StockTopViewRenderer(env.unwrapped_metaworld.model, env.unwrapped_metaworld.data, image_size)
    rates: dict[str, list[float]] = {"physics": [], "rendered": [], "stock": []}
    redraws = []
    length = env.max_episode_steps
    try:
        for rep in range(repeats):
            print(f"bench render: {task} {policy} repeat {rep + 1}/{repeats}", file=sys.stderr, flush=True)
            spent = {"physics": 0.0, "rendered": 0.0, "stock": 0.0}
            done = {"physics": 0, "stock": 0}
            before = getattr(env.renderer, "redraws", 0)
            episode = 0
            while done["physics"] < steps:
                n = min(length, steps - done["physics"])
                ep_seed = seed + 1000 * rep + episode
                spent["physics"] += _time_episode(env, "physics", n, policy, ep_seed)
                spent["rendered"] += _time_episode(env, "rendered", n, policy, ep_seed)
                done["physics"] += n
                if stock is not None and done["stock"] < stock_steps:
                    m = min(n, stock_steps - done["stock"])
                    spent["stock"] += _time_episode(env, "stock", m, policy, ep_seed, stock)
                    done["stock"] += m
                episode += 1
            redraws.append((getattr(env.renderer, "redraws", 0) - before) / steps)
            rates["physics"].append(steps / spent["physics"])
            rates["rendered"].append(steps / spent["rendered"])
            if stock is not None:
                rates["stock"].append(done["stock"] / spent["stock"])
    finally:
        if stock is not None:
            stock.close()
        env.close()
    physics = statistics.median(rates["physics"])
    rendered = statistics.median(rates["rendered"])
    ratios = [r / p for r, p in zip(rates["rendered"], rates["physics"])]
    row = {
        "task": task,
        "image_size": image_size,
        "policy": policy,
        "backend": backend,
        "physics_steps_per_s": round(physics, 1),
        "rendered_steps_per_s": round(rendered, 1),
        "stock_rendered_steps_per_s": round(statistics.median(rates["stock"]), 1) if stock is not None else None,
        "rendered_to_physics": round(statistics.median(ratios), 3),
        "redraw_fraction": round(statistics.median(redraws), 3) if backend == "numpy" else None,
        "target_ratio": TARGET_RATIO,
        "meets_target": statistics.median(ratios) >= TARGET_RATIO,
        "steps": steps,
        "repeats": repeats,
    }
    if stock is not None:
        row["stock_to_physics"] = round(row["stock_rendered_steps_per_s"] / physics, 3)
        row["rendered_to_stock"] = round(rendered / row["stock_rendered_steps_per_s"], 2)
    return row


def render_agreement(task: str, image_size: int = 64, states: int = 10, seed: int = 0) -> dict[str, Any]:
    """Numpy rasterizer vs MuJoCo's GL camera of the same view over an expert episode.

    ``segmentation_agreement``: fraction of pixels where both see the same geom/site;
    ``color_mae``: mean absolute difference of the colour images (0..255), disc included.
    """
    from ..envs.gl_render import GLTopDownRenderer
    from ..envs.metaworld_suite import DISC_RADIUS, MetaWorldTask, robot_bodies, table_geoms

    env = MetaWorldTask(task, "e", image_size=image_size)
    mw = env.unwrapped_metaworld
    raster = env.renderer
    gl = GLTopDownRenderer(mw.model, mw.data, env.view, robot_bodies(mw.model), table_geoms(mw.model))
    agree, mae = [], []
    try:
        env.reset(seed=seed)
        every = max(env.max_episode_steps // states, 1)
        for t in range(env.max_episode_steps):
            if t % every == 0:
                ours = raster.render(mw.tcp_center, DISC_RADIUS)
                theirs = gl.render(mw.tcp_center, DISC_RADIUS)
                agree.append(float((raster.last_ids == gl.segmentation()).mean()))
                mae.append(float(np.abs(ours.astype(np.int16) - theirs.astype(np.int16)).mean()))
            env.step(env.expert_action())
    finally:
        gl.close()
        env.close()
    return {
        "task": task,
        "image_size": image_size,
        "states": len(agree),
        "segmentation_agreement": round(min(agree), 4),
        "segmentation_agreement_mean": round(float(np.mean(agree)), 4),
        "color_mae": round(float(np.mean(mae)), 3),
    }


def save_d4_grid(
    path: str, tasks: list[str], image_size: int = 64, seed: int = 0, steps: int = 25, scale: int = 3, palette: str = "task"
) -> None:
    """PNG grid: one row per task, one column per D4 element, each the transformed task's own image.

    Every cell comes from its own transformed env after the same ``steps`` expert steps from the
    same seed (so the blue gripper disc has left the centre).
    """
    from PIL import Image, ImageDraw

    from ..envs.metaworld_suite import TASKS, MetaWorldTask
    from ..symmetry import D4_ELEMENTS

    pad, label_w, head_h = 4, 150, 18
    cell = image_size * scale
    grid = Image.new("RGB", (label_w + 8 * (cell + pad), head_h + len(tasks) * (cell + pad)), (255, 255, 255))
    draw = ImageDraw.Draw(grid)
    for j, g in enumerate(D4_ELEMENTS):
        draw.text((label_w + j * (cell + pad) + cell // 2 - 6, 3), g.name, fill=(0, 0, 0))
    for i, task in enumerate(tasks):
        y = head_h + i * (cell + pad)
        draw.text((4, y + cell // 2 - 12), f"{TASKS[task].label}\n{task}", fill=(0, 0, 0))
        for j, g in enumerate(D4_ELEMENTS):
            env = MetaWorldTask(task, g, image_size=image_size, palette=palette)
            obs, _ = env.reset(seed=seed)
            for _ in range(steps):
                obs = env.step(env.expert_action())[0]
            env.close()
            img = Image.fromarray(obs["image"]).resize((cell, cell), Image.NEAREST)
            grid.paste(img, (label_w + j * (cell + pad), y))
    grid.save(path)


def run(args: argparse.Namespace) -> int:
    if args.steps < 1 or args.repeats < 1 or args.stock_steps < 1:
        raise SystemExit("covers-dist bench render: --steps, --stock-steps and --repeats must be >= 1")
    from ..envs.metaworld_suite import MAX_IMAGE_SIZE, MIN_IMAGE_SIZE, TASKS

    unknown = [t for t in args.tasks if t not in TASKS]
    if unknown:
        raise SystemExit(f"covers-dist bench render: unknown task(s) {unknown}; expected some of {list(TASKS)}")
    if not MIN_IMAGE_SIZE <= args.image_size <= MAX_IMAGE_SIZE:
        raise SystemExit(f"covers-dist bench render: --image-size must be {MIN_IMAGE_SIZE}..{MAX_IMAGE_SIZE}")
    if args.grid:
        save_d4_grid(args.grid, args.tasks, args.image_size, args.seed, palette=args.palette)
        print(json.dumps({"grid": args.grid}) if args.json else f"wrote {args.grid}")
        return 0
    policies = ("random", "expert") if args.policy == "both" else (args.policy,)
    for task in args.tasks:
        for policy in policies:
            row = measure_task(
                task, args.image_size, args.steps, args.stock_steps, args.repeats, policy,
                args.backend, not args.no_stock, args.seed,
            )
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                stock = row["stock_rendered_steps_per_s"]
                print(
                    f"{task:24s} {policy:6s} {args.image_size}px  physics {row['physics_steps_per_s']:7,.0f}/s  "
                    f"rendered {row['rendered_steps_per_s']:7,.0f}/s  ({row['rendered_to_physics']:.2f}x physics)"
                    + (f"  stock {stock:5,.0f}/s" if stock is not None else ""),
                    flush=True,
                )
        if args.agreement:
            agreement = render_agreement(task, args.image_size, seed=args.seed)
            print(json.dumps(agreement) if args.json else f"{task:24s} agreement with GL: {agreement}", flush=True)
    return 0
