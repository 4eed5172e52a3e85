"""``covers-dist bench assign``: latency of one assignment step against bank and buffer size.

``--stream`` measures the rule on streams with training encoders instead (false splits, ARI,
wrong-policy episodes; see :mod:`covers_dist.bench._assign_stream`).

For each metric, bank size (policies) and buffer size, a bank is filled with that many policies
whose buffers are full, then ``PolicyBank.assign`` is timed on a new batch ``O`` of as many frames
as a buffer holds (the paper's setting is 128 x 128; ``--obs-frames`` sets another size, e.g. 4
for the default config's ``update_every=4`` episodes x ``initial_frames=1``). Features are
``--dim``-wide vectors carried in the observations' proprio (the feature function is the
identity), so the figures are the assignment itself: distances to every policy, the decision,
the buffer update. Encoder passes are the network's cost and are measured with the network.

For scale, the same run times one update step's worth of toy rollout (``--rollout-steps`` env
steps; default ``clustering.update_every * env.max_episode_steps`` of the config, 400 by
default) and reports assignment / rollout ratios.

``--ari`` measures clustering quality instead: the ARI on the toy stream (3 groups x 8 D4
elements in random order, see :mod:`covers_dist.bench.toy_stream`) with untrained encoders
of each kind, for each metric at its threshold, with the config's network, feature source,
feature normalization and ``update_every`` (episodes per assignment).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from ..clustering import METRIC_NAMES, PolicyBank, SharedFeatures
from ..commands._common import add_config_args, config_from_args
from ..config import DEFAULT_THRESHOLDS, Config
from ..envs.toy import ToyTask


def _int_list(low: int, what: str):
    """An argparse type: comma-separated integers, each >= ``low``."""

    def parse(text: str) -> list[int]:
        try:
            values = [int(x) for x in text.split(",") if x.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
        if not values or min(values) < low:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return values

    return parse


_ints = _int_list(1, "positive integers")
_ints_or_zero = _int_list(0, "integers >= 0")


def _metrics(text: str) -> list[str]:
    names = [x.strip() for x in text.split(",") if x.strip()]
    bad = [n for n in names if n not in METRIC_NAMES]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"unknown metric(s) {bad or text!r}; expected some of {list(METRIC_NAMES)}")
    return names


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("assign", help="assignment latency vs bank size and buffer size, per metric")
    p.add_argument("--metrics", type=_metrics, default=list(METRIC_NAMES), help="comma-separated (default: all)")
    p.add_argument("--policies", type=_ints, default=[1, 4, 16, 64], help="bank sizes (default: 1,4,16,64)")
    p.add_argument("--buffers", type=_ints, default=[32, 64, 128, 256, 512], help="buffer sizes (default: 32..512)")
    p.add_argument("--dim", type=int, default=64, help="feature width (default: 64)")
    p.add_argument("--repeats", type=int, default=5, help="timed assignments per cell; median reported (default: 5)")
    p.add_argument("--obs-frames", type=int, default=0, help="frames in O (default 0: as many as a buffer holds)")
    p.add_argument(
        "--rollout-steps", type=int, default=0, help="toy env steps of the reference rollout (default: one update's)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument("--json", action="store_true", help="print one JSON object per line")
    p.add_argument(
        "--ari",
        action="store_true",
        help="instead of latency: ARI on the toy stream (3 groups x 8 D4 elements) per metric and encoder kind",
    )
    p.add_argument("--seeds", type=_ints_or_zero, default=[0, 1, 2], help="--ari: stream/encoder seeds (default: 0,1,2)")
    p.add_argument("--kinds", default="equivariant,cnn", help="--ari: encoder kinds (default: equivariant,cnn)")
    p.add_argument(
        "--stream",
        action="store_true",
        help="instead of latency: false splits, ARI and wrong-policy episodes on streams with training encoders",
    )
    p.add_argument(
        "--streams",
        default="toy-one,toy-multi",
        help="--stream: toy-one,toy-multi,metaworld-one,metaworld-multi,metaworld-mono",
    )
    p.add_argument(
        "--rules", default=None, help="--stream: decision rules (default: the --config's own, else threshold,calibrated)"
    )
    p.add_argument(
        "--assign-at", default=None, help="--stream: assignment moments (default: the --config's own, else iteration,reset)"
    )
    p.add_argument(
        "--steps",
        type=int,
        default=0,
        help="--stream: env steps per run (default: 8000 on toy streams; 16 segments of the config on Meta-World ones)",
    )
    p.add_argument(
        "--batch", type=int, default=0, help="--stream: episodes per assignment (default: the --config's update_every, else 4)"
    )
    add_config_args(p)
    p.set_defaults(func=run)


def _batch(rng: np.random.Generator, n: int, dim: int, centre: float) -> dict[str, np.ndarray]:
    return {
        "image": np.zeros((n, 8, 8, 3), dtype=np.uint8),
        "proprio": (rng.normal(size=(n, dim)) + centre).astype(np.float32),
    }


def filled_bank(metric: str, policies: int, buffer: int, dim: int, seed: int) -> PolicyBank:
    """A bank of ``policies`` entries with full buffers (cluster ``i`` centred at ``10 * i``)."""
    rng = np.random.default_rng(seed)
    # Filled in ground-truth mode (one policy per group, no distances), then switched to the metric.
    bank = PolicyBank(
        SharedFeatures(lambda obs: obs["proprio"]),
        metric=metric,
        threshold=1e9,
        buffer_size=buffer,
        max_policies=max(policies, 1),
        mode="ground_truth",
        seed=seed,
    )
    for i in range(policies):
        bank.assign(_batch(rng, buffer, dim, 10.0 * i), episode_indices=list(range(i * buffer, (i + 1) * buffer)), group_ids=i)
    bank.mode = "distance"
    return bank


def time_assign(bank: PolicyBank, frames: int, dim: int, repeats: int, seed: int) -> float:
    """Median wall time (ms) of ``bank.assign`` on fresh batches near policy 0."""
    rng = np.random.default_rng(seed + 1)
    times = []
    for _ in range(repeats):
        obs = _batch(rng, frames, dim, 0.0)
        t0 = time.perf_counter()
        bank.assign(obs)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def time_rollout(steps: int, repeats: int, seed: int) -> float:
    """Median wall time (ms) of ``steps`` toy env steps with random actions (rendering included)."""
    env = ToyTask("push", "rf", image_size=32)
    actions = np.random.default_rng(seed).uniform(-1, 1, size=(steps, 2)).astype(np.float32)
    times = []
    for _ in range(max(repeats, 3)):
        env.reset(seed=seed)
        t0 = time.perf_counter()
        for a in actions:
            if env.step(a)[3]:
                env.reset()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _threshold(cfg: Config, metric: str) -> float:
    return DEFAULT_THRESHOLDS[metric] if cfg.clustering.threshold is None else cfg.clustering.threshold


def run_ari(args: argparse.Namespace, cfg: Config) -> int:
    """ARI of the toy stream with untrained encoders, per metric x kind (see the module doc)."""
    from .toy_stream import run_toy_stream

    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    if not kinds or any(k not in ("equivariant", "cnn") for k in kinds):
        raise SystemExit(f"covers-dist bench assign: --kinds must list equivariant and/or cnn, got {args.kinds!r}")
    c = cfg.clustering
    for kind in kinds:
        for metric in args.metrics:
            aris = []
            for seed in args.seeds:
                row = run_toy_stream(
                    metric, kind, _threshold(cfg, metric), c.feature_norm, c.feature_source, seed=seed,
                    episodes_per_batch=c.update_every, buffer_size=c.buffer_size, net_cfg=cfg.network,
                )
                row.pop("confusion")
                aris.append(row["ari"])
                if args.json:
                    print(json.dumps(row), flush=True)
                else:
                    print(f"{kind:11s} {metric:11s} seed {seed}: ARI {row['ari']:.3f}, {row['policies']} policies, "
                          f"{row['episodes']} episodes, {row['seconds']:.1f} s", flush=True)
            summary = {
                "kind": kind, "metric": metric, "threshold": _threshold(cfg, metric), "feature_norm": c.feature_norm,
                "source": c.feature_source, "channels": cfg.network.channels, "hidden": cfg.network.hidden,
                "seeds": args.seeds, "ari_mean": round(float(np.mean(aris)), 3), "ari_min": round(float(np.min(aris)), 3),
            }
            print(json.dumps(summary) if args.json else f"  -> mean ARI {summary['ari_mean']:.3f} (min {summary['ari_min']:.3f})")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.stream:
        from ._assign_stream import run as run_stream

        return run_stream(args)
    cfg = config_from_args(args)
    if args.ari:
        return run_ari(args, cfg)
    if args.dim < 1 or args.repeats < 1 or args.rollout_steps < 0 or args.obs_frames < 0:
        raise SystemExit("covers-dist bench assign: --dim and --repeats must be >= 1, --rollout-steps and --obs-frames >= 0")
    steps = args.rollout_steps or cfg.steps_per_update
    rollout_ms = time_rollout(steps, args.repeats, args.seed)
    head = {"reference": "toy_rollout", "steps": steps, "median_ms": round(rollout_ms, 2)}
    print(json.dumps(head) if args.json else f"reference: {steps} toy env steps take {rollout_ms:.1f} ms (median)")
    if not args.json:
        print(f"{'metric':12s} {'policies':>8s} {'buffer':>6s} {'assign ms':>10s} {'ms/policy':>10s} {'/ rollout':>10s}")
    for metric in args.metrics:
        for policies in args.policies:
            for buffer in args.buffers:
                frames = args.obs_frames or buffer
                bank = filled_bank(metric, policies, buffer, args.dim, args.seed)
                time_assign(bank, frames, args.dim, 1, args.seed + 7)  # warm-up
                ms = time_assign(bank, frames, args.dim, args.repeats, args.seed)
                row = {
                    "metric": metric,
                    "policies": policies,
                    "buffer_size": buffer,
                    "obs_frames": frames,
                    "dim": args.dim,
                    "median_ms": round(ms, 3),
                    "ms_per_policy": round(ms / policies, 3),
                    "ratio_to_rollout": round(ms / rollout_ms, 4),
                    "repeats": args.repeats,
                }
                if args.json:
                    print(json.dumps(row), flush=True)
                else:
                    print(
                        f"{metric:12s} {policies:8d} {buffer:6d} {ms:10.2f} {ms / policies:10.3f} {ms / rollout_ms:10.3f}",
                        flush=True,
                    )
    return 0
