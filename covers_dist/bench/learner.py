"""``covers-dist bench learner``: PPO update and rollout-inference throughput, equivariant vs CNN.

For each suite (toy at 32 px, Meta-World at 64 px) and each network (the equivariant net, its
CNN twin at a similar parameter count, and a CNN with the equivariant net's channel count for
context), measured in one run with the networks interleaved in every repeat (medians reported):

* ``update_samples_per_s``: samples per second through one PPO update (forward + backward +
  Adam, minibatches of ``--minibatch``, one epoch over ``--samples`` samples);
* ``infer_obs_per_s_b{1,W,8,16}``: observations per second through ``act`` (the exported no-grad
  path) at batch 1, the worker batch ``W`` (``runtime.envs_per_worker``), 8 and 16.

Also measured, interleaved with the above: the suite's env steps/s in one process (a transformed
toy task; a transformed Meta-World task with its arm-free rendering). ``--equivariance`` adds the
largest relative equivariance error of each output over the group's elements (train, eval and
exported inference paths; the CNN twin for contrast) on real observations of the suite.

Targets: equivariant update throughput >= 0.5 x the CNN twin's, and inference at the worker batch
>= the env steps/s (so inference is not the rollout bottleneck). Results: docs/research/models.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from typing import Any

import numpy as np

from ..config import EnvConfig, NetworkConfig, PPOConfig, RuntimeConfig
from ..symmetry import get_group

UPDATE_RATIO_TARGET = 0.5
SUITES = {"toy": ("reach", 32), "metaworld": ("reach-v3", 64)}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("learner", help="PPO update and inference throughput, equivariant vs CNN twin")
    p.add_argument("--suites", default="toy,metaworld", help="comma-separated suites (default: toy,metaworld)")
    p.add_argument("--samples", type=int, default=1024, help="samples per timed update (default: 1024)")
    p.add_argument("--minibatch", type=int, default=PPOConfig().minibatch_size, help="minibatch size (default: 256)")
    p.add_argument("--repeats", type=int, default=3, help="repeats; medians are reported (default: 3)")
    p.add_argument("--channels", default=None, help="override network.channels, e.g. 4,8,8,16")
    p.add_argument("--hidden", type=int, default=None, help="override network.hidden")
    p.add_argument("--inference-seconds", type=float, default=0.5, help="time per inference figure (default: 0.5)")
    p.add_argument("--env-steps", type=int, default=300, help="env steps timed per suite (default: 300)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: 1, as in a worker)")
    p.add_argument(
        "--space-to-depth", default="1,2",
        help="comma-separated stems to measure in the same run (network.space_to_depth; default: 1,2)",
    )
    p.add_argument(
        "--precision", default="auto", choices=["auto", "fp32", "bf16"],
        help="update arithmetic (ppo.precision; default: auto = bf16 only where it is native)",
    )  # fmt: skip
    p.add_argument(
        "--device", default="cpu",
        help="torch device of the networks and the update, e.g. cpu or cuda (default: cpu); the env timer stays on the CPU",
    )  # fmt: skip
    p.add_argument("--equivariance", action="store_true", help="also print equivariance errors per output")
    p.add_argument("--json", action="store_true", help="print one JSON object per row")
    p.set_defaults(func=run)


def _layout(suite: str, size: int):
    from ..envs import suite_layout

    return suite_layout(suite, size)


def _synthetic_episodes(model: Any, n_samples: int, rng: np.random.Generator, steps: int = 50) -> list[dict]:
    layout = model.layout
    s = layout.image_size
    episodes = []
    for start in range(0, n_samples, steps):
        t = min(steps, n_samples - start)
        obs = {
            "image": rng.integers(0, 256, size=(t + 1, s, s, 3), dtype=np.uint8),
            "proprio": rng.normal(size=(t + 1, layout.proprio_dim)).astype(np.float32),
        }
        actions, logp, values = model.act(obs)
        episodes.append(
            {**obs, "action": actions[:t], "logprob": logp[:t], "value": values,
             "reward": rng.normal(size=t).astype(np.float32), "success": np.zeros(t, np.float32),
             "terminated": False, "truncated": True}
        )  # fmt: skip
    return episodes


def _inference_rate(model: Any, batch: int, seconds: float, rng: np.random.Generator) -> float:
    s = model.layout.image_size
    obs = {
        "image": rng.integers(0, 256, size=(batch, s, s, 3), dtype=np.uint8),
        "proprio": rng.normal(size=(batch, model.layout.proprio_dim)).astype(np.float32),
    }
    model.act(obs)  # warm-up (and export)
    n, start = 0, time.perf_counter()
    while True:
        model.act(obs)
        n += batch
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return n / elapsed


class _EnvTimer:
    """Steps one transformed task of the suite with random actions (images rendered every step)."""

    def __init__(self, suite: str, task: str, size: int) -> None:
        from ..envs import make_task

        self.env, self.error = None, None
        try:
            self.env = make_task(EnvConfig(suite=suite, tasks=[task], image_size=size), task, "r", seed=0)
        except Exception as exc:  # reported in the summary row: the figure is then missing
            self.error = f"{type(exc).__name__}: {exc}"
        self.rng = np.random.default_rng(0)

    def rate(self, steps: int) -> float | None:
        if self.env is None:
            return None
        low, high = self.env.action_space.low, self.env.action_space.high
        actions = self.rng.uniform(low, high, size=(steps, *low.shape)).astype(np.float32)
        elapsed = 0.0
        for a in actions:
            start = time.perf_counter()
            *_, term, trunc, _ = self.env.step(a)
            elapsed += time.perf_counter() - start
            if term or trunc:
                self.env.reset()
        return steps / elapsed

    def close(self) -> None:
        if self.env is not None:
            self.env.close()


def bench_suite(suite: str, net_cfg: NetworkConfig, args: argparse.Namespace) -> list[dict[str, Any]]:
    from ..models import build_actor_critic
    from ..ppo import PPOLearner

    task, size = SUITES[suite]
    layout = _layout(suite, size)
    order = get_group(net_cfg.group).order
    nets = {
        "equivariant": build_actor_critic(net_cfg, layout, "equivariant", seed=0),
        "cnn": build_actor_critic(net_cfg, layout, "cnn", seed=0),
        "cnn_matched_channels": build_actor_critic(
            dataclasses.replace(net_cfg, cnn_width=float(order)), layout, "cnn", seed=0
        ),
    }
    nets = {name: model.to(args.device) for name, model in nets.items()}
    ppo_cfg = PPOConfig(epochs=1, minibatch_size=args.minibatch, precision=args.precision)
    worker_batch = RuntimeConfig().envs_per_worker
    batches = sorted({1, worker_batch, 8, 16})
    rng = np.random.default_rng(0)
    data = {name: _synthetic_episodes(m, args.samples, rng) for name, m in nets.items()}
    learners = {name: PPOLearner(m, ppo_cfg) for name, m in nets.items()}
    samples: dict[str, dict[str, list[float]]] = {n: {"update": []} | {f"b{b}": [] for b in batches} for n in nets}
    env_timer, env_rates = _EnvTimer(suite, task, size), []
    try:
        for _ in range(args.repeats):
            for name, model in nets.items():
                samples[name]["update"].append(learners[name].update(data[name])["samples_per_s"])
                for b in batches:
                    samples[name][f"b{b}"].append(_inference_rate(model, b, args.inference_seconds, rng))
            env_rates.append(env_timer.rate(args.env_steps))
    finally:
        env_timer.close()
    env_rate = None if env_timer.env is None else statistics.median(env_rates)
    env_error = env_timer.error
    rows = []
    for name, model in nets.items():
        med = {k: statistics.median(v) for k, v in samples[name].items()}
        rows.append(
            {"kind": "net", "suite": suite, "net": name, "image_size": size, "group": net_cfg.group, "device": str(args.device),
             "space_to_depth": net_cfg.space_to_depth, "precision": learners[name].precision,
             "params": model.num_parameters(), "feature_dim": model.feature_dim,
             "update_samples_per_s": round(med["update"], 1),
             **{f"infer_obs_per_s_b{b}": round(med[f"b{b}"], 1) for b in batches}}
        )  # fmt: skip
    eq, cnn = rows[0], rows[1]
    ratio = eq["update_samples_per_s"] / cnn["update_samples_per_s"]
    infer_w = eq[f"infer_obs_per_s_b{worker_batch}"]
    rows.append(
        {"kind": "summary", "suite": suite, "image_size": size, "space_to_depth": net_cfg.space_to_depth,
         "update_ratio_equivariant_to_cnn": round(ratio, 3),
         "update_ratio_equivariant_to_cnn_matched_channels": round(
             eq["update_samples_per_s"] / rows[2]["update_samples_per_s"], 3),
         **{f"infer_ratio_equivariant_to_cnn_b{b}": round(eq[f"infer_obs_per_s_b{b}"] / cnn[f"infer_obs_per_s_b{b}"], 3)
            for b in batches},
         "update_target": UPDATE_RATIO_TARGET, "update_target_met": ratio >= UPDATE_RATIO_TARGET,
         "worker_batch": worker_batch, "env_task": task,
         "env_steps_per_s": None if env_rate is None else round(env_rate, 1), "env_error": env_error,
         "inference_over_env": None if env_rate is None else round(infer_w / env_rate, 2),
         "inference_target_met": None if env_rate is None else infer_w >= env_rate,
         "repeats": args.repeats, "threads": args.threads, "samples": args.samples, "minibatch": args.minibatch,
         "device": str(args.device)}
    )  # fmt: skip
    return rows


def _stem_comparison(suite: str, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Update throughput of each stem against the first one measured (the same run)."""
    eq = [r for r in rows if r["kind"] == "net" and r["net"] in ("equivariant", "cnn")]
    base = {r["net"]: r for r in eq if r["space_to_depth"] == eq[0]["space_to_depth"]}
    return [
        {"kind": "stem", "suite": suite, "net": r["net"], "space_to_depth": r["space_to_depth"],
         "baseline_space_to_depth": base[r["net"]]["space_to_depth"],
         "update_speedup": round(r["update_samples_per_s"] / base[r["net"]]["update_samples_per_s"], 3)}
        for r in eq if r["space_to_depth"] != base[r["net"]]["space_to_depth"]
    ]  # fmt: skip


def _env_observations(suite: str, task: str, size: int, n: int = 4) -> dict[str, np.ndarray]:
    """``n`` observations of the base task after a few random steps (different seeds)."""
    from ..envs import make_task

    images, proprios = [], []
    for seed in range(n):
        env = make_task(EnvConfig(suite=suite, tasks=[task], image_size=size), task, "e", seed=seed)
        rng = np.random.default_rng(seed)
        obs = env.reset(seed=seed)[0]
        for _ in range(5):
            obs = env.step(rng.uniform(env.action_space.low, env.action_space.high).astype(np.float32))[0]
        images.append(obs["image"])
        proprios.append(obs["proprio"])
        env.close()
    return {"image": np.stack(images), "proprio": np.stack(proprios)}


def equivariance_rows(suite: str, net_cfg: NetworkConfig) -> list[dict[str, Any]]:
    """Largest relative error over the non-identity elements, per output, mode and network."""
    from ..models import build_actor_critic, equivariance_errors

    task, size = SUITES[suite]
    obs = _env_observations(suite, task, size)
    rows = []
    for kind, modes in (("equivariant", ("train", "eval", "fast")), ("cnn", ("train",))):
        model = build_actor_critic(net_cfg, _layout(suite, size), kind, seed=0)
        for mode in modes:
            model.train(mode == "train")
            errors = equivariance_errors(model, obs, group=net_cfg.group, fast=mode == "fast")
            worst = {k: max(row[k] for g, row in errors.items() if g != "e") for k in errors["e"]}
            rows.append(
                {"kind": "equivariance", "suite": suite, "net": kind, "mode": mode, "group": net_cfg.group,
                 "observations": len(obs["image"]),
                 **{f"max_rel_error_{k}": float(f"{v:.3g}") for k, v in worst.items()}}
            )  # fmt: skip
    return rows


def _print_table(rows: list[dict[str, Any]]) -> None:
    for row in rows:
        if row["kind"] == "stem":
            print(f"{row['suite']:9s} {row['net']:11s} space_to_depth {row['space_to_depth']} update "
                  f"{row['update_speedup']:.2f}x of space_to_depth {row['baseline_space_to_depth']}")
        elif row["kind"] == "equivariance":
            errs = "  ".join(
                f"{k.removeprefix('max_rel_error_')} {v:.1e}" for k, v in row.items() if k.startswith("max_")
            )
            print(f"{row['suite']:9s} {row['net']:11s} {row['mode']:5s} max relative equivariance error: {errs}")
        elif row["kind"] == "net":
            infer = "  ".join(f"{k.split('_')[-1]} {v:8,.0f}" for k, v in row.items() if k.startswith("infer_"))
            print(
                f"{row['suite']:9s} {row['device']:5s} {row['image_size']:3d}px s2d {row['space_to_depth']} {row['net']:21s} params {row['params']:7,d}  "
                f"update {row['update_samples_per_s']:8,.0f} samples/s  infer obs/s: {infer}"
            )
        else:
            env = "n/a" if row["env_steps_per_s"] is None else f"{row['env_steps_per_s']:,.0f}"
            print(
                f"{row['suite']:9s} equivariant/cnn update ratio {row['update_ratio_equivariant_to_cnn']:.2f} "
                f"(target >= {UPDATE_RATIO_TARGET}: {'met' if row['update_target_met'] else 'MISSED'}); "
                f"vs matched-channel CNN {row['update_ratio_equivariant_to_cnn_matched_channels']:.2f}; "
                f"env {env} steps/s, inference at batch {row['worker_batch']} / env = {row['inference_over_env']}"
            )
            if row["env_error"]:
                print(f"  env measurement failed: {row['env_error']}")


def run(args: argparse.Namespace) -> int:
    import torch  # imported here: `covers-dist --help` should not pay for torch

    if args.samples < 1 or args.repeats < 1 or args.minibatch < 1 or args.threads < 1:
        raise SystemExit("covers-dist bench learner: --samples, --repeats, --minibatch and --threads must be >= 1")
    suites = [s.strip() for s in args.suites.split(",") if s.strip()]
    unknown = [s for s in suites if s not in SUITES]
    if unknown or not suites:
        raise SystemExit(f"covers-dist bench learner: unknown suites {unknown}; expected some of {list(SUITES)}")
    net_cfg = NetworkConfig()
    if args.channels:
        net_cfg = dataclasses.replace(net_cfg, channels=[int(c) for c in args.channels.split(",")])
    if args.hidden:
        net_cfg = dataclasses.replace(net_cfg, hidden=args.hidden)
    try:
        stems = [int(k) for k in args.space_to_depth.split(",") if k.strip()]
    except ValueError:
        stems = []
    if not stems or any(k not in (1, 2, 4) for k in stems):
        raise SystemExit(f"covers-dist bench learner: --space-to-depth takes values among 1, 2, 4, got {args.space_to_depth!r}")
    try:
        device = torch.device(args.device)
        torch.empty(1, device=device)
    except (RuntimeError, AssertionError) as exc:
        raise SystemExit(f"covers-dist bench learner: --device {args.device!r} is not usable here: {exc}") from None
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        for suite in suites:
            rows = []
            for k in stems:
                stem_cfg = dataclasses.replace(net_cfg, space_to_depth=k)
                rows += bench_suite(suite, stem_cfg, args)
                if args.equivariance:
                    rows += equivariance_rows(suite, stem_cfg)
            rows += _stem_comparison(suite, rows)
            if args.json:
                for row in rows:
                    print(json.dumps(row), flush=True)
            else:
                _print_table(rows)
    finally:
        torch.set_num_threads(threads)
    return 0
