"""``covers-dist plot RUN_DIR``: figures of a run, written into the run directory.

* ``success_return.png``: success and return per task group over env steps (moving average);
* ``policy_timeline.png``: the policy id of every episode over time, coloured by its true group
  (the clustering at a glance: one policy per colour band is a perfect clustering);
* ``ari_policies.png``: the ARI and the number of policies over env steps;
* ``ppo_updates.png``: the training return and the health of the PPO updates over env steps
  (approximate KL, clip fraction, explained variance, the share of mean actions outside the
  action box); a policy whose
  updates tear it (KL and clip fraction high) or whose mean leaves the box shows here first
  (:func:`ppo_update_figure` draws several runs in one figure);

and, when the run has evaluation passes (``eval.jsonl``):

* ``eval_heatmap.png``: greedy success of every (task, g) at the latest pass, policy chosen by the
  bank (held-out pairs marked H, unseen U);
* ``eval_success.png``: evaluation success of each group over env steps (its mean over every
  (task, g) and its worst (task, g), the figure ``eval.stop_at`` judges), with the moments each
  group appears in the stream (dotted lines in its colour) and the average over groups seen.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plot", help="write PNG figures of a run (success, return, policy timeline, ARI)")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory written by covers-dist train")
    p.add_argument("--window", type=int, default=10, help="moving-average window in episodes (default: 10)")
    p.set_defaults(func=run)


def _read_jsonl(run: Path, name: str) -> list[dict[str, Any]]:
    """Rows of log ``name`` of the run: its rotated segments, then the live file."""
    from ..runtime.logfiles import has_log, read_jsonl_segments

    if not has_log(run, name):
        raise SystemExit(f"covers-dist plot: {run / name} is missing (is this a run directory?)")
    try:
        return list(read_jsonl_segments(run, name))
    except ValueError as e:
        raise SystemExit(f"covers-dist plot: {e}") from None


def _dedupe(rows: list[dict[str, Any]], key: str) -> list[dict[str, Any]]:
    """Keep the last row per key (a resumed run may repeat the iterations after its checkpoint)."""
    by_key = {r[key]: r for r in rows if key in r}
    return [by_key[k] for k in sorted(by_key)]


def _moving(x: np.ndarray, w: int) -> np.ndarray:
    if len(x) == 0:
        return x
    w = max(1, min(w, len(x)))
    c = np.cumsum(np.insert(x, 0, 0.0))
    out = np.empty_like(x, dtype=float)
    out[w - 1 :] = (c[w:] - c[:-w]) / w
    out[: w - 1] = c[1:w] / np.arange(1, w)
    return out


def make_plots(run_dir: str | Path, window: int = 10) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = Path(run_dir)
    episodes = _dedupe(_read_jsonl(run, "episodes.jsonl"), "episode_index")
    metrics = _dedupe(_read_jsonl(run, "metrics.jsonl"), "iteration")
    if not episodes or not metrics:
        raise SystemExit(f"covers-dist plot: {run} has no episodes yet")
    # env steps at the end of every episode (episodes of one iteration share a logged step count)
    steps_at = dict(zip([e["episode_index"] for e in episodes], np.cumsum([e["length"] for e in episodes])))
    tasks = sorted({e["task"] for e in episodes}, key=lambda t: min(e["group_id"] for e in episodes if e["task"] == t))
    colors = {t: plt.cm.tab10(i % 10) for i, t in enumerate(tasks)}
    out: list[Path] = []

    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for t in tasks:
        rows = [e for e in episodes if e["task"] == t]
        steps = np.array([steps_at[e["episode_index"]] for e in rows])
        axes[0].plot(steps, _moving(np.array([e["success"] for e in rows], float), window), label=t, color=colors[t])
        axes[1].plot(steps, _moving(np.array([e["return"] for e in rows], float), window), label=t, color=colors[t])
    axes[0].set(xlabel="env steps", ylabel=f"success (moving avg, {window} episodes)", ylim=(-0.05, 1.05))
    axes[1].set(xlabel="env steps", ylabel=f"return (moving avg, {window} episodes)")
    for ax in axes:
        ax.legend(title="task group")
        ax.grid(alpha=0.3)
    fig.suptitle(f"{run.name}: success and return per task group")
    out.append(_save(fig, run / "success_return.png"))

    fig, ax = plt.subplots(figsize=(12, 3.5))
    for t in tasks:
        rows = [e for e in episodes if e["task"] == t]
        ax.scatter(
            [e["episode_index"] for e in rows], [e.get("assigned_policy", e["policy_id"]) for e in rows],
            s=10, color=colors[t], label=t,
        )
    ax.set(xlabel="episode", ylabel="assigned policy id", title="policy id of every episode, coloured by true group")
    ax.yaxis.get_major_locator().set_params(integer=True)
    ax.legend(title="true group", loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    out.append(_save(fig, run / "policy_timeline.png"))

    fig, ax = plt.subplots(figsize=(8, 3.5))
    steps = [m["env_steps"] for m in metrics]
    ax.plot(steps, [np.nan if m.get("ari") is None else m["ari"] for m in metrics], color="tab:blue", label="ARI")
    ax.set(xlabel="env steps", ylabel="adjusted Rand index", ylim=(-0.1, 1.05))
    ax2 = ax.twinx()
    ax2.step(steps, [m["num_policies"] for m in metrics], color="tab:orange", where="post", label="policies")
    ax2.set_ylabel("number of policies")
    ax2.yaxis.get_major_locator().set_params(integer=True)
    fig.legend(loc="lower right")
    ax.grid(alpha=0.3)
    ax.set_title("clustering quality and bank size")
    out.append(_save(fig, run / "ari_policies.png"))
    out.append(_ppo_update_figure({run.name: metrics}, run / "ppo_updates.png", window))
    out += eval_plots(run, episodes, colors)
    return out


#: (metrics.jsonl key, panel title, log scale) of :func:`ppo_update_figure`.
PPO_PANELS = (
    ("ppo/approx_kl", "approximate KL per update", True),
    ("ppo/clip_frac", "clip fraction", False),
    ("ppo/explained_variance", "critic's explained variance", False),
    ("ppo/mean_out_of_box", "share of mean actions outside [-1, 1]", False),
)


def ppo_update_figure(runs: dict[str, str | Path], path: str | Path, window: int = 10) -> Path:
    """The training return and the PPO update statistics over env steps (moving average over
    ``window`` iterations), one colour per run (``{label: run directory}``); a statistic a run did
    not log is left out of its panel."""
    series = {label: _dedupe(_read_jsonl(Path(d), "metrics.jsonl"), "iteration") for label, d in runs.items()}
    return _ppo_update_figure(series, path, window)


def _ppo_update_figure(series: dict[str, list[dict[str, Any]]], path: str | Path, window: int) -> Path:
    """:func:`ppo_update_figure` on metrics rows already read (``{label: rows}``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = len(PPO_PANELS) + 1
    fig, axes = plt.subplots(1, panels, figsize=(4.0 * panels, 3.4))
    for i, (label, metrics) in enumerate(series.items()):
        color = plt.cm.tab10(i % 10)
        returns = [(m["env_steps"], np.mean([v for k, v in m.items() if k.startswith("return/")])) for m in metrics
                   if any(k.startswith("return/") for k in m)]  # fmt: skip
        if returns:
            x, y = zip(*returns)
            axes[0].plot(x, _moving(np.array(y, float), window), color=color, label=label)
        for ax, (key, _, _) in zip(axes[1:], PPO_PANELS):
            rows = [m for m in metrics if isinstance(m.get(key), (int, float)) and np.isfinite(m[key])]
            if rows:
                ax.plot([m["env_steps"] for m in rows], _moving(np.array([m[key] for m in rows], float), window),
                        color=color, label=label)  # fmt: skip
    axes[0].set(title="training return (episode mean)", xlabel="env steps")
    axes[0].grid(alpha=0.3)
    for ax, (key, title, log) in zip(axes[1:], PPO_PANELS):
        ax.set(title=title, xlabel="env steps")
        if log and ax.lines:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    if axes[0].lines:
        axes[0].legend(fontsize=8)
    fig.suptitle(f"PPO updates (moving average over {window} iterations)")
    return _save(fig, Path(path))


def eval_plots(run: Path, episodes: list[dict[str, Any]], colors: dict[str, Any]) -> list[Path]:
    """The evaluation figures (see the module doc); [] when the run has no evaluation pass."""
    import matplotlib.pyplot as plt

    from ..evaluation import read_passes
    from ..evaluation.metrics import group_success, group_worst, pass_summary

    try:
        passes = read_passes(run)
    except ValueError as e:
        raise SystemExit(f"covers-dist plot: {e}") from None
    if not passes:
        return []
    last = passes[-1]
    tasks = list(dict.fromkeys(r["task"] for r in last["pairs"]))
    elements = list(dict.fromkeys(r["g"] for r in last["pairs"]))
    grid = np.full((len(tasks), len(elements)), np.nan)
    marks = {}
    for r in last["pairs"]:
        i, j = tasks.index(r["task"]), elements.index(r["g"])
        res = r.get("results", {}).get("greedy/agnostic")
        if res is not None:
            grid[i, j] = res["success"]
        marks[i, j] = {"held_out": "H", "unseen": "U"}.get(r["status"], "")
    fig, ax = plt.subplots(figsize=(1.1 * len(elements) + 3, 0.7 * len(tasks) + 1.8))
    im = ax.imshow(grid, vmin=0.0, vmax=1.0, cmap="viridis", aspect="auto")
    for (i, j), m in marks.items():
        v = grid[i, j]
        ax.text(j, i, ("n/a" if np.isnan(v) else f"{v:.2f}") + (f" {m}" if m else ""), ha="center", va="center",
                color="white" if np.isnan(v) or v < 0.6 else "black", fontsize=8)  # fmt: skip
    ax.set_xticks(range(len(elements)), elements)
    ax.set_yticks(range(len(tasks)), tasks)
    ax.set(xlabel="group element g", title=f"greedy success per (task, g), iteration {last.get('iteration')} "
           "(H held-out, U not trained yet)")  # fmt: skip
    fig.colorbar(im, ax=ax, label="success")
    paths = [_save(fig, run / "eval_heatmap.png")]

    fig, ax = plt.subplots(figsize=(10, 4))
    steps = [ev.get("env_steps", 0) for ev in passes]
    for t in tasks:
        color = colors.get(t)
        ax.plot(steps, [np.nan if (v := group_success(ev, t)) is None else v for ev in passes], "o-", label=t,
                color=color)  # fmt: skip
        ax.plot(steps, [np.nan if (v := group_success(ev, t, key="greedy/oracle")) is None else v for ev in passes],
                ":", color=color, alpha=0.6)  # fmt: skip
        ax.plot(steps, [np.nan if (v := group_worst(ev, t)) is None else v for ev in passes], "--", color=color,
                alpha=0.8)  # fmt: skip
    avg = [pass_summary(ev)["average_success"] for ev in passes]
    ax.plot(steps, [np.nan if v is None else v for v in avg], "k--", label="average (groups seen)")
    steps_at = dict(zip([e["episode_index"] for e in episodes], np.cumsum([e["length"] for e in episodes])))
    prev = None
    for e in episodes:  # the start of every stream segment, in its group's colour
        if e["task"] != prev and e["episode_index"] in steps_at:
            ax.axvline(steps_at[e["episode_index"]] - e["length"], color=colors.get(e["task"], "grey"), ls=":", lw=1)
        prev = e["task"]
    ax.set(xlabel="env steps", ylabel="greedy success (evaluation)", ylim=(-0.05, 1.05),
           title="greedy success: solid mean, dashed worst (task, g), dotted oracle policy; vertical: group switches")  # fmt: skip
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    paths.append(_save(fig, run / "eval_success.png"))
    return paths


def _steps_label(x: float, _pos: Any = None) -> str:
    """An env-step tick as 0, 50k, 1.2M: full numbers overlap on a narrow panel."""
    if abs(x) >= 1e6:
        return f"{x / 1e6:g}M"
    return f"{x / 1e3:g}k" if abs(x) >= 1e3 else f"{x:g}"


def _save(fig: Any, path: Path) -> Path:
    from matplotlib.ticker import FuncFormatter

    for ax in fig.axes:
        if ax.get_xlabel() == "env steps":
            ax.xaxis.set_major_formatter(FuncFormatter(_steps_label))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def run(args: argparse.Namespace) -> int:
    for path in make_plots(args.run_dir, args.window):
        print(path)
    return 0
