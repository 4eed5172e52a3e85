"""``covers-dist bench learn``: time and env steps until the greedy policy solves a task group.

One task group is one base task (e.g. ``drawer-close-v3``) under every element of the config's
symmetry group (D4: 8 transformed tasks). Each contender trains on a stream of that task alone,
every episode under a group element, and is evaluated every ``--eval-every`` env steps with the
clock paused. It is **solved** once the greedy policy (the Gaussian's mean) succeeds on at least
``--threshold`` of the evaluation episodes of *every* transform at two consecutive evaluations
(one lucky point on a noisy curve does not stop a run); otherwise it runs until its budget of env
steps or training minutes is spent. Contenders run one after another, never at once:

* ``covers``: covers-dist's own loop (:class:`covers_dist.runtime.driver.Trainer`) with the config as
  given (the equivariant network), on Ray (``--serial``: in one process);
* ``cnn``: the same loop with the CNN twin (``runtime.method=covers-cnn``, ``network.kind=cnn``);
* ``rllib-cnn``: RLlib's PPO on the project's CNN twin (``CoversRLModule``, image + proprio);
* ``rllib-equi``: RLlib's PPO on the project's equivariant network (``CoversRLModule``, image + proprio);
* ``rllib-default``: RLlib's PPO with its default CNN on the image alone, for reference;
* ``sb3``: Stable-Baselines3's PPO, ``MultiInputPolicy`` on image + proprio
  (:mod:`covers_dist.bench.sb3_peer`).

Every peer runs on equal terms (:func:`covers_dist.bench.rllib_peer.ppo_settings`): the same batch,
epochs, minibatch, learning rate and schedule (a linear one ends with each contender's own step
budget: every contender runs with ``runtime.total_env_steps`` = its budget), gamma, lambda, clip,
gradient clip, entropy and value coefficients, covers-dist's reward treatment (scale, return
normalisation), no value clip unless the config has one; with ``ppo.target_kl``, SB3 stops its
updates at the same approximate KL and RLlib, which has no such stop, gets its KL loss instead.
``result.json`` prints each contender's effective ``hyperparameters``, read back from the built algorithm. Peers get a budget of at least
``--peer-budget-factor`` (default 4) times the training time and env steps covers-dist needed
when ``covers`` ran first in the same invocation and was solved, so a peer's miss is a figure,
not a bound.

The covers-dist stream is ``env.tasks: [TASK]`` with ``env.episodes_per_task: 1`` and
``env.held_out: 0``: every episode is a new segment, and the elements come in seeded shuffles of
the group (each run of |G| episodes holds every element once; :class:`~covers_dist.envs.stream.TaskStream`).
The peers' envs draw an element uniformly at each reset, seeded from the reset's seed.

**Evaluation** (the same for all contenders, :class:`GroupEvaluation`): the project's one evaluator
(:func:`covers_dist.evaluation.run_evaluation`, episodes by
:func:`covers_dist.evaluation.episodes.run_eval_episodes`), ``--eval-episodes`` (default 16)
greedy episodes on each element, each (element, episode) reset with its own seed
(:func:`covers_dist.evaluation.protocol.eval_seed`; the same seeds at every point and for every
contender), so a point rests on |G| x episodes distinct initial states; each point records
``distinct_initial_states`` (counted from the states' fingerprints) and, per transform, its ``n``
and Wilson 95% interval. An episode succeeds when ``info["success"]`` was ever true; where the
env says how close it came (Meta-World's ``obj_to_target`` over the success radius), the point
also records ``misses``: per transform, its failures' median closest approach in radii and how
many were near misses (the progress line counts them). Before each
evaluation the covers loop waits for the update in flight (its time counts as training) and its
newest weights act without being published, so the run trains exactly as it would without the
evaluation. Each transform is evaluated with the policy the bank would choose from the
evaluation episodes' first frames (``what_if``, the bank unchanged; when it would create a new
policy, the nearest one). A peer's greedy policy plugs in through
:class:`~covers_dist.evaluation.episodes.GreedyPolicy`: RLlib's module (``forward_inference``'s
Gaussian mean, unsquashed and clipped as RLlib's connector does), SB3's ``predict(deterministic=True)``.

**Clock**: ``train_wall_s`` counts the seconds spent in training calls (``Trainer.step`` and
the wait for the update in flight, ``Algorithm.train``, ``PPO.learn``), not the start-up (actors,
learners, env runners; reported as ``setup_s``) nor the evaluations (``eval_s``).
``--budget-minutes`` bounds that training clock.

**Separate invocations** (``--merge A/result.json B/result.json``): contenders run apart (say
``covers`` first, the peers later) are joined into one result with its ratios and curves,
provided they agree on the task, group, transforms, threshold and evaluation protocol.

**Seeds summed up** (``--table A/result.json B/result.json ...``): runs of the same settings on
several seeds and task groups become one row per (task group, contender): how many seeds held,
and the median and range of the env steps and training minutes to held. A run that did not hold
counts as later than every run that did (its time is censored at the budget), so the median is a
figure only when at least half the seeds held.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import statistics
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Mapping, NoReturn, Sequence

import numpy as np

from ..commands._common import CommaList

PROG = "covers-dist bench learn"
CONTENDERS: tuple[str, ...] = ("covers", "cnn", "rllib-cnn", "rllib-equi", "rllib-default", "sb3")
#: The peers (frameworks other than covers-dist's loop) and what each runs.
PEERS: dict[str, dict[str, str]] = {
    "rllib-cnn": {"framework": "rllib", "network": "covers", "kind": "cnn"},
    "rllib-equi": {"framework": "rllib", "network": "covers", "kind": "equivariant"},
    "rllib-default": {"framework": "rllib", "network": "default", "kind": ""},
    "sb3": {"framework": "sb3", "network": "", "kind": ""},
}
#: Overrides that turn the config into each covers-dist contender.
CONTENDER_OVERRIDES: dict[str, list[str]] = {
    "covers": [],
    "cnn": ["runtime.method=covers-cnn", "network.kind=cnn"],
    "rllib-cnn": ["runtime.method=covers-cnn", "network.kind=cnn"],
}
#: Curves per task that ``--figure`` still labels inside the axes; more go in a legend below them.
LEGEND_INSIDE = 5
#: Evaluations in a row that must meet the threshold for a run to count as solved.
HELD_EVALUATIONS = 2
#: What a curve point keeps of each transform's failed episodes (``covers_dist.evaluation.stats.miss_summary``).
MISS_KEYS = ("misses", "misses_closest_median", "near_misses")
#: Versions of the weight averages an evaluation acts with count down from here (never a published one).
AVERAGED_VERSION = -(2**40)

#: A greedy policy: a batch of observations (``image`` uint8 (B, S, S, 3), ``proprio`` (B, P)) ->
#: the actions (B, A) to send to the envs.
ActFn = Callable[[Mapping[str, np.ndarray]], np.ndarray]

__all__ = [
    "GroupEvaluation", "CONTENDERS", "PEERS", "register", "run", "plot_curves", "ratios", "merge_results",
    "results_figure", "results_table", "format_table",
]


# ---- the command line --------------------------------------------------------------------------
def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "learn",
        help="time and env steps until the greedy policy solves every transform of one task group, vs RLlib",
    )
    p.add_argument("--config", default="configs/quickstart.yaml", help="config (default: configs/quickstart.yaml)")
    p.add_argument("--task", default=None, help="base task of the group (default: the config's first task)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every contender (repeatable)")  # fmt: skip
    p.add_argument("--seed", type=int, default=None, help="run seed (default: the config's)")
    p.add_argument("--threshold", type=float, default=0.9,
                   help="success needed on every transform, 0 < t <= 1 (default: 0.9)")  # fmt: skip
    p.add_argument("--eval-every", type=int, default=4000, help="env steps between evaluations (default: 4000)")
    p.add_argument("--eval-episodes", type=int, default=16,
                   help="greedy episodes per transform, each from its own initial state (default: 16)")  # fmt: skip
    p.add_argument("--budget-steps", type=int, default=200_000, help="env steps per contender (default: 200000)")
    p.add_argument("--budget-minutes", type=float, default=45.0,
                   help="training minutes per contender, evaluations excluded (default: 45)")  # fmt: skip
    p.add_argument("--contenders", default=",".join(CONTENDERS),
                   help="comma-separated subset of: " + ", ".join(CONTENDERS) + " (default: all)")  # fmt: skip
    p.add_argument("--peer-budget-factor", type=float, default=4.0,
                   help="when covers ran first here and was solved, each peer's budget is at least this many times "
                        "covers' training time and env steps (default: 4)")  # fmt: skip
    p.add_argument("--serial", action="store_true", help="covers-dist contenders in one process (runtime.serial)")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last stdout line")
    p.add_argument("--plot", default=None, metavar="PATH.png", help="draw the success curves there")
    p.add_argument("--out", default=None, metavar="DIR", help="write result.json and curves.png there")
    p.add_argument("--keep-runs", action="store_true",
                   help="keep each covers-dist contender's run directory as DIR/runs/NAME (needs --out): "
                        "its metrics, checkpoints and `covers-dist plot` figures")  # fmt: skip
    p.add_argument("--merge", action=CommaList, default=None, metavar="RESULT.json",
                   help="train nothing: join the contenders of earlier result.json files (comma-separated) of one "
                        "task group (same task, group, threshold and evaluation) into one result, its ratios and "
                        "curves")  # fmt: skip
    p.add_argument("--figure", action=CommaList, default=None, metavar="RESULT.json",
                   help="train nothing: draw the curves of earlier result.json files (comma-separated; any task "
                        "groups, seeds and settings) into --plot, a panel per task group, one line per result "
                        "and contender")  # fmt: skip
    p.add_argument("--table", action=CommaList, default=None, metavar="RESULT.json",
                   help="train nothing: per task group and contender, the seeds that held and the median and "
                        "range of env steps and training minutes to held, over earlier result.json files of one "
                        "setting (comma-separated); a Markdown table, or JSON with --json")  # fmt: skip
    p.add_argument("--labels", action=CommaList, default=None, metavar="LABEL",
                   help="with --figure: one label per result file (default: its seed and the overrides the "
                        "others do not share)")  # fmt: skip
    p.set_defaults(func=run)


def _fail(message: str) -> NoReturn:
    """A one-line usage error on stderr, exit status 2."""
    print(f"{PROG}: {message}", file=sys.stderr)
    raise SystemExit(2)


def _check_args(args: argparse.Namespace) -> list[str]:
    """Validate the options that need no config; the contenders to run, in the order given."""
    if not (isinstance(args.threshold, float) and math.isfinite(args.threshold) and 0.0 < args.threshold <= 1.0):
        _fail(f"--threshold must be in (0, 1], got {args.threshold}")
    for flag, value in (("--eval-every", args.eval_every), ("--eval-episodes", args.eval_episodes),
                        ("--budget-steps", args.budget_steps)):  # fmt: skip
        if value < 1:
            _fail(f"{flag} must be >= 1, got {value}")
    factor = getattr(args, "peer_budget_factor", 4.0)
    if not (math.isfinite(factor) and factor >= 1.0):
        _fail(f"--peer-budget-factor must be >= 1, got {factor}")
    if not (math.isfinite(args.budget_minutes) and args.budget_minutes > 0):
        _fail(f"--budget-minutes must be > 0, got {args.budget_minutes}")
    if args.seed is not None and args.seed < 0:
        _fail(f"--seed must be >= 0, got {args.seed}")
    if getattr(args, "keep_runs", False) and not args.out:
        _fail("--keep-runs needs --out DIR (the runs are kept as DIR/runs/NAME)")
    chosen = list(dict.fromkeys(c.strip() for c in args.contenders.split(",") if c.strip()))
    if not chosen:
        _fail(f"--contenders is empty; choose from {list(CONTENDERS)}")
    unknown = [c for c in chosen if c not in CONTENDERS]
    if unknown:
        _fail(f"unknown contender(s) {unknown}; choose from {list(CONTENDERS)}")
    return chosen


def _log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


# ---- evaluation ------------------------------------------------------------------------------
class GroupEvaluation:
    """``bench learn``'s evaluation of one task group: every element, ``episodes`` greedy episodes each.

    A thin host around the project's evaluator (:func:`covers_dist.evaluation.run_evaluation` on one
    in-process :class:`~covers_dist.runtime.rollout.RolloutWorker`): the pairs are (task, g) for
    every element of the group (group id 0, the stream's only group), reset with the protocol's
    seeds, a distinct initial state per (element, episode).
    """

    def __init__(self, cfg: Any, task: str, elements: Sequence[str], episodes: int, seed: int) -> None:
        from ..evaluation import LocalExecutors
        from ..evaluation.protocol import EvalPair
        from ..runtime.rollout import EVAL_WORKER_INDEX, RolloutWorker

        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        if not elements:
            raise ValueError("no group elements to evaluate")
        self.task, self.episodes, self.seed = task, int(episodes), int(seed)
        self.elements = [str(g) for g in elements]
        self.pairs = [EvalPair(task, g, 0, j, "seen") for j, g in enumerate(self.elements)]
        self.executors = LocalExecutors([RolloutWorker(cfg, EVAL_WORKER_INDEX)])

    def evaluate(self, contender: Any) -> dict[str, Any]:
        """One pass with ``contender``'s ``choose`` and ``weights_map()``; per element its success,
        ``n``, 95% interval and policy, and the pass's ``distinct_initial_states``."""
        from ..evaluation import run_evaluation

        ev = run_evaluation(
            self.executors,
            self.pairs,
            contender.choose,
            {},
            contender.weights_map(),
            self.seed,
            self.episodes,
            modes=("greedy",),
            selections=("agnostic",),
        )
        per = {row["g"]: row["results"].get("greedy/agnostic") for row in ev["pairs"]}
        missing = [g for g, res in per.items() if res is None]
        if missing:
            raise RuntimeError(f"no policy could act on transform(s) {missing}")
        from ..evaluation.stats import wilson_interval

        k, n = sum(int(res["successes"]) for res in per.values()), sum(int(res["n"]) for res in per.values())
        misses = {g: {key: res[key] for key in MISS_KEYS} for g, res in per.items() if "misses" in res}
        return {
            "misses": misses,  # per transform with failures: how close they came (success radii)
            "success": {g: float(res["success"]) for g, res in per.items()},
            "ci95": {g: res["ci95"] for g, res in per.items()},
            "pooled": {"successes": k, "n": n, "ci95": [round(x, 4) for x in wilson_interval(k, n)]},
            "policy": {g: res["policy_id"] for g, res in per.items()},  # the policy acting most episodes
            "episode_policies": {row["g"]: row.get("episode_policies") for row in ev["pairs"]},
            "episodes_per_transform": self.episodes,
            "distinct_initial_states": int(ev["distinct_initial_states"]),
        }

    def close(self) -> None:
        self.executors.close()


def rllib_actor(module: Any, action_space: Any, normalize_actions: bool = True, image_only: bool = True) -> ActFn:
    """The greedy policy of an RLlib RLModule: the mean of its diagonal Gaussian
    (``action_dist_inputs`` = ``[mean, log_std]``), unsquashed (``normalize_actions``) and clipped to
    ``action_space`` as RLlib's module-to-env connector does. ``image_only``: the module takes the
    image as floats in [0, 1] (RLlib's default CNN); else the task's dict (image + proprio)."""
    import torch
    from ray.rllib.core.columns import Columns
    from ray.rllib.utils.spaces.space_utils import unsquash_action

    dim = int(np.prod(action_space.shape))

    def act(obs: Mapping[str, np.ndarray]) -> np.ndarray:
        if image_only:
            inputs: Any = torch.from_numpy(np.asarray(obs["image"], dtype=np.float32) * (1.0 / 255.0))
        else:
            inputs = {"image": torch.from_numpy(np.asarray(obs["image"])),
                      "proprio": torch.from_numpy(np.asarray(obs["proprio"], dtype=np.float32))}  # fmt: skip
        with torch.no_grad():
            out = module.forward_inference({Columns.OBS: inputs})
        mean = out[Columns.ACTION_DIST_INPUTS][:, :dim].cpu().numpy().astype(np.float32)
        if normalize_actions:
            return np.stack([unsquash_action(a, action_space) for a in mean]).astype(np.float32)
        return np.clip(mean, action_space.low, action_space.high)

    return act


def _only_policy(obs: Mapping[str, np.ndarray], group_ids: Sequence[int]) -> dict[str, Any]:
    """A peer has one policy: it acts on every transform."""
    return {"policy_id": 0, "decision": "only", "nearest_distance": None}


# ---- contenders ------------------------------------------------------------------------------
class _CoversContender:
    """covers-dist's loop (:class:`~covers_dist.runtime.driver.Trainer`) on the serial or Ray backend."""

    def __init__(self, cfg: Any, keep: bool = False) -> None:
        from ..runtime.driver import Trainer
        from ..runtime.metrics import MetricsWriter

        self.cfg = cfg
        self.trainer = Trainer(cfg, log=lambda *_: None)
        # a kept run logs as `covers-dist train` does (metrics.jsonl, episodes.jsonl; a checkpoint at the end)
        self.writer = MetricsWriter(self.trainer.run_dir, tensorboard=False) if keep else None
        self.trainer.start_policy(0)  # as Trainer.run starts: policy 0's learner and weights
        backend = self.trainer.backend
        if getattr(backend, "name", "") == "ray":  # wait until the rollout actors are up: start-up, not training
            backend.ray.get([w.stats.remote() for w in backend.workers])
        self._weights: dict[int, tuple[int, Any]] = {}  # what the evaluation acts with (before_eval)
        # ppo.weight_average: the evaluation acts with each policy's moving average of its weights, and the
        # newest weights are evaluated beside it on the same initial states (shadows)
        self.averaged = cfg.ppo.weight_average is not None
        self._shadows: dict[str, dict[int, tuple[int, Any]]] = {}
        self._evals = 0

    @property
    def env_steps(self) -> int:
        return int(self.trainer.env_steps)

    def train_once(self) -> None:
        row = self.trainer.step()
        if self.writer is not None:
            self.trainer.write_iteration(self.writer, row)

    def before_eval(self) -> None:
        # the newest weights, without publishing the update in flight: training goes on exactly as
        # it would without this evaluation (the run does not depend on --eval-every)
        self._weights = self.trainer.newest_weights()
        if self.averaged:
            self._evals += 1
            self._shadows = {"newest": self._weights}
            version = AVERAGED_VERSION - self._evals  # never a version the workers or an earlier pass hold
            call = self.trainer.backend.call_learner
            self._weights = {pid: (version, call(pid, "averaged_weights")[1]) for pid in self._weights}

    def weights_map(self) -> dict[int, tuple[int, Any]]:
        return dict(self._weights)

    def shadows(self) -> dict[str, dict[int, tuple[int, Any]]]:
        """Other weights evaluated at each point beside the contender's own: ``{"newest": ...}`` when
        the evaluation acts with the moving average (``ppo.weight_average``), else none."""
        return dict(self._shadows)

    def choose(self, first_frames: Mapping[str, np.ndarray], group_ids: Sequence[int]) -> dict[str, Any]:
        """The policy the bank would pick for these first frames (the only one when it holds one;
        the nearest existing one when the rule would create a policy)."""
        policies = sorted(self._weights)
        if len(policies) == 1:
            return {"policy_id": policies[0], "decision": "only", "nearest_distance": None}
        n = len(first_frames["image"])
        record = self.trainer.backend.call_clustering("what_if", dict(first_frames), [0] * n, policies)
        pid = int(record["policy_id"])
        if pid not in self._weights:
            dists = {int(k): float(v) for k, v in (record.get("distances") or {}).items() if v is not None}
            dists = {k: v for k, v in dists.items() if k in self._weights}
            pid = min(dists, key=lambda k: dists[k]) if dists else int(self.trainer.current_policy)
        return {"policy_id": pid, "decision": record.get("decision"), "nearest_distance": record.get("nearest_distance")}

    def extra(self) -> dict[str, Any]:
        return {"num_policies": len(self.trainer.weights.versions)}

    def hyperparameters(self) -> dict[str, Any]:
        from .rllib_peer import ppo_settings

        cfg = self.cfg
        return {
            "framework": "covers-dist",
            "network": f"covers-dist {cfg.network.kind}, channels {list(cfg.network.channels)}, hidden {cfg.network.hidden}"
            + ("" if cfg.network.critic == "shared" else f", {cfg.network.critic} critic"),
            "observation": "image + proprio",
            **ppo_settings(cfg),
            "normalize_advantages": "per minibatch" if cfg.ppo.norm_adv else False,
            "rollout_workers": cfg.runtime.num_workers,
            "envs_per_worker": cfg.runtime.envs_per_worker,
            **({} if cfg.ppo.log_std_cap is None else {"log_std_cap": float(cfg.ppo.log_std_cap)}),
            **({} if cfg.ppo.ent_schedule == "constant" else {"ent_schedule": cfg.ppo.ent_schedule}),
            **({} if cfg.ppo.kl_reference == "behaviour" else {"kl_reference": cfg.ppo.kl_reference}),
            **({} if cfg.ppo.noise_beta == 0.0 else {"noise_beta": float(cfg.ppo.noise_beta)}),
            **({} if cfg.ppo.noise_fade_success is None else {"noise_fade_success": float(cfg.ppo.noise_fade_success)}),
            **({} if cfg.ppo.noise_fraction == 1.0 else {"noise_fraction": float(cfg.ppo.noise_fraction)}),
            **({} if cfg.ppo.noise_entries == "all" else {"noise_entries": cfg.ppo.noise_entries}),
            **({} if cfg.ppo.weight_average is None else {"weight_average": float(cfg.ppo.weight_average)}),
        }

    def close(self) -> None:
        try:
            if self.writer is not None:
                self.trainer.checkpoint()
                self.writer.close()
        finally:
            self.trainer.close()


class _PeerContender:
    """What the peers share: one policy acting on every transform, nothing in flight at an evaluation."""

    iterations = 0
    _hp: dict[str, Any] = {}

    choose = staticmethod(_only_policy)

    def before_eval(self) -> None:
        """Nothing in flight: a peer's training call returns after its update."""

    def extra(self) -> dict[str, Any]:
        return {"iterations": self.iterations}

    def hyperparameters(self) -> dict[str, Any]:
        return dict(self._hp)


class _RLlibContender(_PeerContender):
    """RLlib's PPO (new API stack) on the group's transforms, with the network ``PEERS[name]`` names."""

    def __init__(self, name: str, cfg: Any, elements: Sequence[str]) -> None:
        from .rllib_peer import build_rllib_ppo, rllib_hyperparameters

        peer = PEERS[name]
        self.network = peer["network"]
        self.cfg = cfg
        self.algo = build_rllib_ppo(cfg, self.network, transforms=list(elements))
        self._hp = rllib_hyperparameters(self.algo, self.network, cfg)
        self.steps = 0
        self.iterations = 0

    @property
    def env_steps(self) -> int:
        return self.steps

    def train_once(self) -> None:
        from ray.rllib.utils.metrics import ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED

        result = self.algo.train()
        self.steps += int(result[ENV_RUNNER_RESULTS][NUM_ENV_STEPS_SAMPLED])
        self.iterations += 1

    def weights_map(self) -> dict[int, tuple[int, Any]]:
        from ..evaluation.episodes import GreedyPolicy

        module = self.algo.get_module()  # the local env runner's copy, synced by every train()
        module.eval()
        act = rllib_actor(module, module.action_space, bool(self.algo.config.normalize_actions),
                          image_only=self.network == "default")  # fmt: skip
        return {0: (self.iterations, GreedyPolicy(act, "rllib"))}

    def close(self) -> None:
        self.algo.stop()


class _SB3Contender(_PeerContender):
    """Stable-Baselines3's PPO (``MultiInputPolicy`` on image + proprio) on the group's transforms."""

    def __init__(self, cfg: Any, elements: Sequence[str]) -> None:
        from .sb3_peer import build_sb3_ppo, sb3_hyperparameters

        self.model = build_sb3_ppo(cfg, list(elements))
        self._hp = sb3_hyperparameters(self.model, cfg)
        self._batch = int(self.model.n_steps * self.model.n_envs)
        self.iterations = 0

    @property
    def env_steps(self) -> int:
        return int(self.model.num_timesteps)

    def train_once(self) -> None:
        # one rollout of n_steps per env and one update, the batch of one covers-dist iteration
        self.model.learn(total_timesteps=self._batch, reset_num_timesteps=False)
        self.iterations += 1

    def weights_map(self) -> dict[int, tuple[int, Any]]:
        from ..evaluation.episodes import GreedyPolicy
        from .sb3_peer import sb3_greedy

        return {0: (self.iterations, GreedyPolicy(sb3_greedy(self.model), "sb3"))}

    def close(self) -> None:
        self.model.get_env().close()


# ---- one race --------------------------------------------------------------------------------
def race(
    name: str,
    contender: Any,
    evaluator: GroupEvaluation,
    threshold: float,
    eval_every: int,
    budget_steps: int,
    budget_s: float,
    log: Callable[[str], None] = _log,
    held: int = HELD_EVALUATIONS,
) -> dict[str, Any]:
    """Train ``contender`` until its greedy policy meets ``threshold`` on every element at ``held``
    consecutive evaluations, or its budget ends; evaluates (clock paused) at 0 env steps and every
    ``eval_every`` env steps, and once more at the end when the last point is older."""
    curve: list[dict[str, Any]] = []
    train_s, eval_s, next_eval = 0.0, 0.0, 0
    streak = 0  # consecutive evaluations at or above the threshold
    reached: dict[str, Any] | None = None
    shadow_streaks: dict[str, int] = {}  # the same, per shadow (weights evaluated beside the contender's own)

    def evaluate() -> dict[str, Any]:
        nonlocal train_s, eval_s, streak
        t0 = time.perf_counter()
        contender.before_eval()
        train_s += time.perf_counter() - t0
        t1 = time.perf_counter()
        out = evaluator.evaluate(contender)
        spent = time.perf_counter() - t1
        eval_s += spent
        values = list(out["success"].values())
        point = {
            "env_steps": contender.env_steps,
            "train_wall_s": round(train_s, 3),
            "eval_s": round(spent, 3),
            "min_success": float(min(values)),
            "mean_success": float(np.mean(values)),
            "success": out["success"],
            "ci95": out["ci95"],
            "pooled": out["pooled"],  # every transform's episodes together: the mean's n and interval
            "misses": out.get("misses", {}),  # an evaluator whose envs say how close episodes came
            "episodes_per_transform": out["episodes_per_transform"],
            "distinct_initial_states": out["distinct_initial_states"],
            "policy": out["policy"],
            **contender.extra(),
        }
        streak = streak + 1 if point["min_success"] >= threshold else 0
        point["held"] = streak
        shadow_txt = ""
        for shadow, weights in (contender.shadows() if hasattr(contender, "shadows") else {}).items():
            t2 = time.perf_counter()
            other = evaluator.evaluate(_FixedWeights(contender.choose, weights))
            spent_shadow = time.perf_counter() - t2
            eval_s += spent_shadow
            got = list(other["success"].values())
            shadow_streaks[shadow] = shadow_streaks.get(shadow, 0) + 1 if min(got) >= threshold else 0
            point.setdefault("shadows", {})[shadow] = {
                "min_success": float(min(got)),
                "mean_success": float(np.mean(got)),
                "success": other["success"],
                "pooled": other["pooled"],
                "held": shadow_streaks[shadow],
                "eval_s": round(spent_shadow, 3),
            }
            shadow_txt += f"{shadow} weights: min {min(got):.2f} mean {np.mean(got):.2f}; "
        curve.append(point)
        steps = point["env_steps"]
        rate = steps / train_s if train_s > 0 else 0.0
        left = budget_steps - steps
        if rate > 0 and left > 0:  # wall-clock time to the step budget, evaluations included
            eta = min(left / rate, max(budget_s - train_s, 0.0)) * (train_s + eval_s) / max(train_s, 1e-9)
            eta_txt = f"ETA {_duration(eta)} to the budget ({budget_steps} steps, {budget_s / 60:g} min of training)"
        else:
            eta_txt = "budget spent" if left <= 0 else "ETA n/a"
        log(
            f"learn {name}: {steps} env steps, {train_s:.1f} s training ({rate:.0f} steps/s), success min "
            f"{point['min_success']:.2f} mean {point['mean_success']:.2f} on {point['distinct_initial_states']} "
            f"initial states ({point['episodes_per_transform']} per transform; eval {spent:.1f} s), "
            f"{_misses_text(point['misses'])}{streak} in a row >= {threshold}; {shadow_txt}{eta_txt}"
        )
        return point

    stopped = "steps"
    while True:
        if contender.env_steps >= next_eval:
            point = evaluate()
            next_eval = (contender.env_steps // eval_every + 1) * eval_every
            if streak >= held:
                reached, stopped = point, "threshold"
                break
        out_of = "steps" if contender.env_steps >= budget_steps else ("minutes" if train_s >= budget_s else None)
        if out_of is not None:
            stopped = out_of
            if curve[-1]["env_steps"] != contender.env_steps:  # the newest policy gets its evaluation too
                point = evaluate()
                if streak >= held:
                    reached, stopped = point, "threshold"
            break
        t0 = time.perf_counter()
        contender.train_once()
        train_s += time.perf_counter() - t0
    final_steps = contender.env_steps
    first_met = curve[-held] if reached is not None else None
    if reached is not None:
        log(f"learn {name}: solved: success >= {threshold} on every transform at {held} evaluations in a row, "
            f"first at {first_met['env_steps']} env steps, held at {reached['env_steps']} env steps, "
            f"{reached['train_wall_s']:.1f} s of training")  # fmt: skip
    else:
        log(f"learn {name}: {stopped} budget spent at {final_steps} env steps, {train_s:.1f} s of training; "
            f"best min success {max(p['min_success'] for p in curve):.2f}")  # fmt: skip
    return {
        "reached": reached is not None,
        "solved_rule": f"min success over transforms >= threshold at {held} consecutive evaluations",
        # the run is known solved at the evaluation that completes the streak: its steps and time count
        "env_steps_to_threshold": reached["env_steps"] if reached else None,
        "wall_s_to_threshold": reached["train_wall_s"] if reached else None,
        "first_met_env_steps": first_met["env_steps"] if first_met else None,
        # the first evaluation at the threshold, held or not (an unsolved run may have met it)
        "first_at_threshold_env_steps": next((p["env_steps"] for p in curve if p["min_success"] >= threshold), None),
        "best_min_success": max(p["min_success"] for p in curve),
        "best_mean_success": max(p["mean_success"] for p in curve),
        "stopped": stopped,
        "env_steps": final_steps,
        "train_wall_s": round(train_s, 3),
        "eval_s": round(eval_s, 3),
        "steps_per_s": round(final_steps / train_s, 1) if train_s > 0 else None,
        "curve": curve,
        **({"shadows": _shadow_summary(curve, threshold, held)} if shadow_streaks else {}),
    }


class _FixedWeights:
    """A contender's bank choice with other weights: what a shadow evaluation acts with."""

    def __init__(self, choose: Callable[..., dict[str, Any]], weights: Mapping[int, tuple[int, Any]]) -> None:
        self.choose, self._weights = choose, dict(weights)

    def weights_map(self) -> dict[int, tuple[int, Any]]:
        return dict(self._weights)


def _shadow_summary(curve: Sequence[Mapping[str, Any]], threshold: float, held: int) -> dict[str, Any]:
    """Per shadow: where it first met ``threshold`` on every transform, where it held (``held`` in a
    row) and its best worst transform, over the points it was evaluated at."""
    out: dict[str, Any] = {}
    for name in sorted({k for p in curve for k in p.get("shadows", {})}):
        points = [(p["env_steps"], p["shadows"][name]) for p in curve if name in p.get("shadows", {})]
        out[name] = {
            "first_at_threshold_env_steps": next((s for s, q in points if q["min_success"] >= threshold), None),
            "env_steps_to_threshold": next((s for s, q in points if q["held"] >= held), None),
            "best_min_success": max(q["min_success"] for _, q in points),
        }
    return out


def _misses_text(misses: Mapping[str, Mapping[str, Any]]) -> str:
    """``failures: 9 (7 within 1.5 success radii); `` of a pass, or nothing when no env reported how close."""
    from ..evaluation.stats import NEAR_MISS

    if not misses:
        return ""
    total = sum(int(m["misses"]) for m in misses.values())
    near = sum(int(m["near_misses"]) for m in misses.values())
    return f"failures: {total} ({near} within {NEAR_MISS:g} success radii); "


def _duration(seconds: float) -> str:
    seconds = max(0.0, float(seconds))
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def _run_contender(
    name: str, cfg: Any, elements: list[str], evaluator: GroupEvaluation, budget: tuple[int, float],
    args: argparse.Namespace, keep: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """Build one contender (Ray started for it and shut down after), race it, tear it down."""
    from ..runtime.ray_setup import init_ray, shutdown_ray

    framework = PEERS.get(name, {}).get("framework", "covers")
    use_ray = framework == "rllib" or (framework == "covers" and not cfg.runtime.serial)
    t0 = time.perf_counter()
    if use_ray:
        init_ray(cfg.runtime.num_cpus, cfg.runtime.ray_address)
    contender: Any = None
    try:
        if framework == "rllib":
            contender = _RLlibContender(name, cfg, elements)
        elif framework == "sb3":
            contender = _SB3Contender(cfg, elements)
        else:
            contender = _CoversContender(cfg, keep)
        setup_s = time.perf_counter() - t0
        _log(f"learn {name}: ready after {setup_s:.1f} s of start-up")
        steps, minutes = budget
        result = race(name, contender, evaluator, args.threshold, args.eval_every, steps, minutes * 60.0)
        result["setup_s"] = round(setup_s, 3)
        result["backend"] = framework if framework != "covers" else ("serial" if cfg.runtime.serial else "ray")
        result["budget"] = {"env_steps": int(steps), "minutes": float(minutes)}
        result["hyperparameters"] = contender.hyperparameters()
        return result
    finally:
        if contender is not None:
            contender.close()
        if use_ray:
            shutdown_ray()


def peer_budget(args: argparse.Namespace, covers: Mapping[str, Any] | None) -> tuple[int, float]:
    """A peer's (env steps, training minutes): the given budget, raised to ``--peer-budget-factor``
    times what covers needed when covers ran before it here and was solved."""
    steps, minutes = int(args.budget_steps), float(args.budget_minutes)
    if covers and covers.get("reached"):
        factor = float(getattr(args, "peer_budget_factor", 4.0))
        steps = max(steps, int(math.ceil(factor * covers["env_steps_to_threshold"])))
        minutes = max(minutes, factor * covers["wall_s_to_threshold"] / 60.0)
    return steps, minutes


# ---- results ---------------------------------------------------------------------------------
def ratios(contenders: Mapping[str, Mapping[str, Any]]) -> dict[str, float | None]:
    """covers / each other contender, in training seconds and env steps to the solved point (below 1:
    covers got there sooner); None where either was not solved (or did not run)."""

    def ratio(a: str, b: str, key: str) -> float | None:
        x, y = contenders.get(a, {}), contenders.get(b, {})
        if not (x.get("reached") and y.get("reached")):
            return None
        top, bottom = x.get(key), y.get(key)
        if top is None or bottom is None or bottom <= 0:
            return None
        return round(float(top) / float(bottom), 3)

    out: dict[str, float | None] = {}
    for other in contenders:
        if other == "covers":
            continue
        key = other.replace("-", "_")
        out[f"covers_wall_vs_{key}"] = ratio("covers", other, "wall_s_to_threshold")
        out[f"covers_steps_vs_{key}"] = ratio("covers", other, "env_steps_to_threshold")
    return out


def plot_curves(result: Mapping[str, Any], path: str | Path) -> Path:
    """Min-over-transforms (solid) and mean (dashed) success of each contender, vs env steps and
    vs training seconds, with the threshold (a shadow's min dotted); written to ``path`` (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for k, (name, res) in enumerate(result["contenders"].items()):
        curve = res.get("curve") or []
        if not curve:
            continue
        color = f"C{k}"
        for ax, key in zip(axes, ("env_steps", "train_wall_s")):
            xs = [p[key] for p in curve]
            ax.plot(xs, [p["min_success"] for p in curve], "-o", color=color, ms=3, label=f"{name} min")
            ax.plot(xs, [p["mean_success"] for p in curve], "--", color=color, alpha=0.7, label=f"{name} mean")
            for shadow in sorted({k for p in curve for k in p.get("shadows", {})}):  # e.g. the newest weights
                pts = [p for p in curve if shadow in p.get("shadows", {})]
                ax.plot([p[key] for p in pts], [p["shadows"][shadow]["min_success"] for p in pts], ":x", color=color,
                        ms=4, label=f"{name} min, {shadow} weights")  # fmt: skip
    for ax, label in zip(axes, ("env steps", "training wall-clock (s)")):
        ax.axhline(result["threshold"], color="grey", lw=0.8, ls=":")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("greedy success over transforms")
    axes[0].set_ylim(-0.03, 1.03)
    axes[1].legend(loc="lower right", fontsize=8)
    fig.suptitle(f"{result['task']} under {result['group']} ({len(result['transforms'])} transforms)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _summary(result: Mapping[str, Any]) -> str:
    lines = [f"{result['task']} under {result['group']}, threshold {result['threshold']}:"]
    for name, res in result["contenders"].items():
        if "error" in res:
            lines.append(f"  {name}: failed: {res['error']}")
            continue
        if res["reached"]:
            what = (f"solved (held at {HELD_EVALUATIONS} evaluations in a row) at {res['env_steps_to_threshold']} env "
                    f"steps, {res['wall_s_to_threshold']:.1f} s")  # fmt: skip
        else:
            what = f"not reached ({res['stopped']} budget spent): best min success {res['best_min_success']:.2f}"
        lines.append(f"  {name}: {what} ({res['env_steps']} env steps, {res['train_wall_s']:.1f} s of training)")
    for key, value in result["ratios"].items():
        if value is not None:
            lines.append(f"  {key}: {value}")
    return "\n".join(lines)


# ---- joining separate invocations ----------------------------------------------------------------
#: What must agree for two results to be compared side by side.
_MERGE_KEYS = ("task", "group", "transforms", "threshold", "eval")


def merge_results(results: Sequence[Mapping[str, Any]], sources: Sequence[str] | None = None) -> dict[str, Any]:
    """One result from the results of separate invocations on the same task group.

    The contenders of every result are joined (each may appear once) and the ratios recomputed.
    Results must agree on :data:`_MERGE_KEYS`; budgets, configs, overrides and seeds may differ and
    are kept per contender (``budget``, ``config``, ``overrides``, ``seed`` under each contender).
    Raises ``ValueError`` naming what does not match.
    """
    names = list(sources) if sources is not None else [f"result {i}" for i in range(len(results))]
    if not results:
        raise ValueError("nothing to merge")
    first = results[0]
    joined: dict[str, Any] = {}
    for name, res in zip(names, results):
        missing = [k for k in (*_MERGE_KEYS, "contenders") if k not in res]
        if missing:
            raise ValueError(f"{name}: not a bench learn result (no {', '.join(missing)})")
        entries = res["contenders"]
        if not isinstance(entries, Mapping) or not all(isinstance(e, Mapping) for e in entries.values()):
            raise ValueError(f"{name}: not a bench learn result (contenders is not an object of objects)")
        for key in _MERGE_KEYS:
            if res[key] != first[key]:
                raise ValueError(f"{name}: {key} {res[key]!r} differs from {names[0]}'s {first[key]!r}")
        for contender, entry in entries.items():
            _check_curve(name, contender, entry)
            if contender in joined:
                raise ValueError(f"{name}: contender {contender!r} appears in more than one result")
            own = {k: res[k] for k in ("budget", "config", "overrides", "seed") if k in res}
            joined[contender] = {**entry, **own}
    merged: dict[str, Any] = {key: first[key] for key in _MERGE_KEYS}
    merged.update(contenders=joined, merged_from=names, ratios=ratios(joined))
    return merged


#: What every point of a contender's curve carries (numbers), for the ratios and the plot.
_POINT_KEYS = ("env_steps", "train_wall_s", "min_success", "mean_success")


def _check_curve(name: str, contender: str, entry: Mapping[str, Any]) -> None:
    """Raise ``ValueError`` unless ``entry["curve"]`` (when present) is a list of complete points."""
    if "error" in entry and "curve" not in entry:  # a contender that failed carries its error, no curve
        return
    curve = entry.get("curve")
    if not isinstance(curve, list):
        raise ValueError(f"{name}: contender {contender!r} has no curve (a list of points)")
    for i, point in enumerate(curve):
        bad = [k for k in _POINT_KEYS if not isinstance(point, Mapping) or not _is_number(point.get(k))]
        if bad:
            raise ValueError(f"{name}: contender {contender!r}, curve point {i} lacks numeric {', '.join(bad)}")


def _check_result(label: str, res: Mapping[str, Any]) -> None:
    """Raise ``ValueError`` unless ``res`` has a task, a threshold and contenders, each contender
    that is an object and did not fail with a complete curve."""
    if not isinstance(res.get("contenders"), Mapping) or "task" not in res or "threshold" not in res:
        raise ValueError(f"{label}: not a bench learn result (no task, threshold or contenders)")
    for contender, entry in res["contenders"].items():
        if isinstance(entry, Mapping) and "error" not in entry:
            _check_curve(label, contender, entry)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _load_result(path: str, flag: str = "--merge") -> dict[str, Any]:
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        _fail(f"{flag}: no such file {path}")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        _fail(f"{flag}: cannot read {path} as JSON: {e}")
    if not isinstance(data, dict):
        _fail(f"{flag}: {path} is not a bench learn result (a JSON object)")
    return data


def _report(result: Mapping[str, Any], args: argparse.Namespace) -> None:
    """Write ``--out`` / ``--plot`` and print the summary (or ``--json``)."""
    plots = [Path(args.plot)] if args.plot else []
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "result.json").write_text(json.dumps(result, indent=1) + "\n")
        plots.append(out / "curves.png")
    for path in plots:
        _log(f"learn: curves written to {plot_curves(result, path)}")
    if args.json:
        print(json.dumps(result))
    else:
        print(_summary(result))


def _merge(args: argparse.Namespace) -> int:
    results = [_load_result(path) for path in args.merge]
    try:
        result = merge_results(results, list(args.merge))
    except ValueError as e:
        _fail(f"--merge: {e}")
    _report(result, args)
    return 0


def results_figure(results: Sequence[tuple[str, Mapping[str, Any]]], path: str | Path) -> Path:
    """Several results in one figure: a panel per task group (in first-seen order), in it one colour
    per (result, contender), the worst transform solid and the mean dashed against env steps, a
    star where a run held the threshold. ``results``: ``(label, result)`` pairs. Raises
    ``ValueError`` naming a result that is not a bench learn result."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..commands.plot import _save  # lays out, formats the env-step axes (50k, 1.2M), writes, closes

    tasks: list[str] = []
    for label, res in results:
        _check_result(label, res)
        tasks += [res["task"]] if res["task"] not in tasks else []
    per_task = [sum(len(res["contenders"]) for _, res in results if res["task"] == t) for t in tasks]
    below = max(per_task) > LEGEND_INSIDE  # many curves: the legend goes under the axes, the figure grows
    height = 3.6 + (0.17 * max(per_task) + 0.3 if below else 0.0)
    fig, axes = plt.subplots(1, len(tasks), figsize=(4.2 * len(tasks), height), sharex=True, sharey=True, squeeze=False)
    colour: dict[str, int] = {}
    for label, res in results:
        ax = axes[0][tasks.index(res["task"])]
        for contender, entry in res["contenders"].items():
            if not isinstance(entry, Mapping) or "error" in entry:
                continue
            name = label if len(res["contenders"]) == 1 else f"{label} {contender}"
            c = f"C{colour.setdefault(name, len(colour)) % 10}"
            curve = entry["curve"]
            xs = [p["env_steps"] for p in curve]
            ax.plot(xs, [p["min_success"] for p in curve], "-o", color=c, ms=3, label=name)
            ax.plot(xs, [p["mean_success"] for p in curve], "--", color=c, alpha=0.5)
            if entry.get("reached"):
                ax.plot([entry["env_steps_to_threshold"]], [1.03], "*", color=c, ms=10)
    for ax, task in zip(axes[0], tasks):
        threshold = next(res["threshold"] for _, res in results if res["task"] == task)
        ax.axhline(threshold, color="grey", lw=0.8, ls=":")
        ax.set(title=task, xlabel="env steps")
        ax.grid(alpha=0.3)
        if below:
            ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=1, frameon=False)
        else:
            ax.legend(fontsize=7, loc="lower right")
    axes[0][0].set_ylabel("greedy success (worst: solid, mean: dashed)")
    axes[0][0].set_ylim(-0.03, 1.08)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return _save(fig, path)


def _default_labels(results: Sequence[Mapping[str, Any]]) -> list[str]:
    """Each result's label in a figure: its seed and the overrides the other results do not share."""
    sets = [[str(o) for o in r.get("overrides") or []] for r in results]
    common = set.intersection(*(set(s) for s in sets)) if sets else set()
    return [" ".join([f"seed {r.get('seed', '?')}", *(o for o in s if o not in common)]) for r, s in zip(results, sets)]


def _figure(args: argparse.Namespace) -> int:
    if not args.plot:
        _fail("--figure: give --plot PATH.png, where the figure goes")
    labels = list(args.labels) if args.labels else None
    if labels is not None and len(labels) != len(args.figure):
        _fail(f"--labels: {len(labels)} labels for {len(args.figure)} result files")
    results = [_load_result(path, "--figure") for path in args.figure]
    pairs = list(zip(labels or _default_labels(results), results))
    try:
        _log(f"learn: figure written to {results_figure(pairs, args.plot)}")
    except ValueError as e:
        _fail(f"--figure: {e}")
    return 0


# ---- seeds summed up -----------------------------------------------------------------------------
#: What the runs summed up in one row must share (besides the task and the contender).
_TABLE_KEYS = ("group", "threshold", "eval", "budget", "config")


def _setting(res: Mapping[str, Any]) -> dict[str, Any]:
    """What a result's runs were trained and judged with, its seed left out."""
    overrides = [str(o) for o in res.get("overrides") or [] if not str(o).startswith("seed=")]
    return {**{k: res.get(k) for k in _TABLE_KEYS}, "overrides": overrides}


def _censored_median(values: Sequence[float], runs: int) -> float:
    """The median of ``runs`` times to held, ``values`` of them observed and the rest later than any
    of them (not held within the budget): ``inf`` when half the runs or more did not hold."""
    return statistics.median([*values, *[math.inf] * (runs - len(values))])


def results_table(results: Sequence[tuple[str, Mapping[str, Any]]]) -> list[dict[str, Any]]:
    """One row per (task group, contender) over ``(source, result)`` pairs of one setting: its seeds,
    how many held, the censored median (:func:`_censored_median`) and the range of env steps and
    training minutes to held over those that did, each seed's worst and mean transform at its last
    evaluation and its env steps per second. Rows in first-seen order. Raises ``ValueError`` naming a
    file that is not a bench learn result, whose setting differs from the first's, or that repeats
    a seed of its row."""
    rows: dict[tuple[str, str], dict[str, Any]] = {}
    first: tuple[str, dict[str, Any]] | None = None
    for source, res in results:
        _check_result(source, res)
        setting = _setting(res)
        if first is None:
            first = (source, setting)
        for key, value in setting.items():
            if value != first[1][key]:
                raise ValueError(f"{source}: {key} {value!r} differs from {first[0]}'s {first[1][key]!r}; "
                                 "a table sums up the seeds of one setting")  # fmt: skip
        for contender, entry in res["contenders"].items():
            if not isinstance(entry, Mapping):
                raise ValueError(f"{source}: not a bench learn result (contender {contender!r} is not an object)")
            if "error" in entry:
                continue
            if entry.get("reached") and not (_is_number(entry.get("env_steps_to_threshold"))
                                             and _is_number(entry.get("wall_s_to_threshold"))):  # fmt: skip
                raise ValueError(f"{source}: contender {contender!r} held but has no env steps or time to held")
            row = rows.setdefault((res["task"], contender),
                                  {"task": res["task"], "contender": contender, "setting": setting, "runs": []})  # fmt: skip
            seed = res.get("seed")
            if any(run["seed"] == seed for run in row["runs"]):
                raise ValueError(f"{source}: seed {seed} of {res['task']} {contender} appears in more than one result")
            last = entry["curve"][-1] if entry["curve"] else {"min_success": 0.0, "mean_success": 0.0}
            row["runs"].append({
                "seed": seed, "source": source, "held": bool(entry.get("reached")),
                "env_steps_to_held": entry.get("env_steps_to_threshold") if entry.get("reached") else None,
                "minutes_to_held": round(entry["wall_s_to_threshold"] / 60.0, 2) if entry.get("reached") else None,
                "last": {k: last.get(k) for k in ("env_steps", "min_success", "mean_success")},
                "steps_per_s": entry.get("steps_per_s"),
            })  # fmt: skip
    for row in rows.values():
        held = [run for run in row["runs"] if run["held"]]
        row.update(seeds=[run["seed"] for run in row["runs"]], held=len(held), n=len(row["runs"]))
        for key in ("env_steps_to_held", "minutes_to_held"):
            values = [float(run[key]) for run in held]
            median = _censored_median(values, len(row["runs"]))
            row[key] = {
                "median": None if math.isinf(median) else round(median, 2),
                "min": min(values) if values else None,
                "max": max(values) if values else None,
            }
    return list(rows.values())


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """:func:`results_table`'s rows as a Markdown table."""
    from ..commands.plot import _steps_label

    def spread(stat: Mapping[str, Any], fmt: Callable[[float], str], row: Mapping[str, Any]) -> str:
        if stat["min"] is None:
            return "-"
        median = "not held" if stat["median"] is None else fmt(stat["median"])
        span = fmt(stat["min"]) if stat["min"] == stat["max"] else f"{fmt(stat['min'])}-{fmt(stat['max'])}"
        later = row["n"] - row["held"]
        return f"{median} ({span}{f'; {later} later than the budget' if later else ''})"

    budget = rows[0]["setting"]["budget"] if rows else None
    within = f"{_steps_label(budget['env_steps'])} env steps or {budget['minutes']:g} min" if budget else "the budget"
    lines = [
        f"| task group | contender | held within {within} | env steps to held: median (range) | "
        "training minutes to held: median (range) | worst/mean transform at the last evaluation, per seed | "
        "env steps/s |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        runs = row["runs"]
        held = ", ".join(f"{run['seed']}" for run in runs if run["held"])
        last = "; ".join(f"seed {run['seed']}: {run['last']['min_success']:.2f}/{run['last']['mean_success']:.2f} at "
                         f"{_steps_label(run['last']['env_steps'] or 0)}" for run in runs)  # fmt: skip
        rates = [run["steps_per_s"] for run in runs if _is_number(run["steps_per_s"])]
        rate = "-" if not rates else f"{min(rates):.0f}" + (f"-{max(rates):.0f}" if max(rates) > min(rates) else "")
        lines.append(
            f"| {row['task']} | {row['contender']} | {row['held']} of {row['n']} (seeds {held or 'none'}) | "
            f"{spread(row['env_steps_to_held'], _steps_label, row)} | "
            f"{spread(row['minutes_to_held'], lambda m: f'{m:.1f}', row)} | {last} | {rate} |"
        )
    return "\n".join(lines)


def _table(args: argparse.Namespace) -> int:
    results = [(path, _load_result(path, "--table")) for path in args.table]
    try:
        rows = results_table(results)
    except ValueError as e:
        _fail(f"--table: {e}")
    print(json.dumps(rows) if args.json else format_table(rows))
    return 0


# ---- the benchmark ---------------------------------------------------------------------------
def run(args: argparse.Namespace) -> int:
    if getattr(args, "table", None):
        return _table(args)
    if getattr(args, "figure", None):
        return _figure(args)
    if getattr(args, "merge", None):
        return _merge(args)
    from ..config import load_config
    from ..envs import task_names
    from ..symmetry import get_group

    chosen = _check_args(args)
    user = list(args.overrides)
    if args.seed is not None:
        user.append(f"seed={args.seed}")
    base = load_config(args.config, user)
    valid = list(task_names(base.env.suite))
    task = args.task if args.task is not None else base.env.tasks[0]
    if task not in valid:
        _fail(f"unknown {base.env.suite} task {task!r} for --task; valid tasks: {', '.join(valid)}")
    elements = [g.name for g in get_group(base.env.group)]
    serial = bool(args.serial or base.runtime.serial)
    # one task group: every episode a new segment (seeded shuffles of the group; --set may change
    # that), no held-out pairs
    overrides = ["env.episodes_per_task=1", *user, f"env.tasks=[{task}]", "env.held_out=0", "eval.tasks=null"]
    cfg0 = load_config(args.config, overrides)
    peers = [n for n in chosen if n in PEERS]
    own = [f"ppo.log_std_cap={cfg0.ppo.log_std_cap}"] * (cfg0.ppo.log_std_cap is not None)
    own += [f"network.critic={cfg0.network.critic}"] * (cfg0.network.critic != "shared")
    own += [f"ppo.ent_schedule={cfg0.ppo.ent_schedule}"] * (cfg0.ppo.ent_schedule != "constant")
    own += [f"ppo.kl_reference={cfg0.ppo.kl_reference}"] * (cfg0.ppo.kl_reference != "behaviour")
    own += [f"ppo.noise_beta={cfg0.ppo.noise_beta}"] * (cfg0.ppo.noise_beta != 0.0)
    if own and peers:
        _fail(
            f"{', '.join(own)}: covers-dist's contenders only; the peers {peers} would train without it. "
            "Run them in another invocation without it, or drop it"
        )
    kept = {n: str(Path(args.out) / "runs" / n) for n in chosen if getattr(args, "keep_runs", False) and n not in PEERS}
    for run_dir in kept.values():
        if Path(run_dir).is_dir() and any(Path(run_dir).iterdir()):
            _fail(f"--keep-runs: {run_dir} already holds a run; choose another --out or remove it")
    evaluator = GroupEvaluation(cfg0, task, elements, args.eval_episodes, cfg0.seed)
    result: dict[str, Any] = {
        "task": task,
        "group": cfg0.env.group,
        "transforms": elements,
        "threshold": args.threshold,
        "budget": {"env_steps": args.budget_steps, "minutes": args.budget_minutes},
        "eval": {
            "every_env_steps": args.eval_every,
            "episodes_per_transform": args.eval_episodes,
            "initial_states": "distinct per (transform, episode)",
            "solved": f"threshold met at {HELD_EVALUATIONS} consecutive evaluations",
        },
        "config": args.config,
        "overrides": list(args.overrides),
        "seed": cfg0.seed,
        "contenders": {},
    }
    _log(
        f"learn: {task} under {cfg0.env.group} ({len(elements)} transforms), threshold {args.threshold}, "
        f"budget {args.budget_steps} env steps / {args.budget_minutes:g} min each, contenders {', '.join(chosen)}"
    )
    failed = False
    try:
        for name in chosen:
            keep = name in kept
            run_dir = kept[name] if keep else tempfile.mkdtemp(prefix=f"covers-learn-{name}-")
            budget = (args.budget_steps, args.budget_minutes)
            if name in PEERS:
                budget = peer_budget(args, result["contenders"].get("covers"))
            # the run's length is the contender's step budget: a linear learning-rate schedule with a
            # null ppo.total_updates ends with it, for covers-dist and each peer alike
            extra = [f"runtime.run_dir={run_dir}", f"runtime.serial={str(serial).lower()}",
                     f"runtime.total_env_steps={int(budget[0])}"]  # fmt: skip
            try:
                cfg = load_config(args.config, [*overrides, *CONTENDER_OVERRIDES.get(name, []), *extra])
                result["contenders"][name] = _run_contender(name, cfg, elements, evaluator, budget, args, keep)
            except KeyboardInterrupt:
                raise
            except Exception as e:  # noqa: BLE001 - reported; the other contenders still run
                failed = True
                _log(f"learn {name}: failed: {type(e).__name__}: {e}\n{traceback.format_exc(limit=6)}")
                result["contenders"][name] = {"reached": False, "error": f"{type(e).__name__}: {e}", "curve": []}
            finally:
                if not keep:
                    shutil.rmtree(run_dir, ignore_errors=True)
    finally:
        evaluator.close()
    result["ratios"] = ratios(result["contenders"])
    _report(result, args)
    return 1 if failed else 0
