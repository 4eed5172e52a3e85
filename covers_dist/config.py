"""One typed, validated configuration tree for covers-dist.

Every hyperparameter lives here, in frozen dataclasses with a docstring per field (the ``doc``
metadata). Configs are loaded from YAML files (a path, or the name of a config shipped in
``covers_dist/configs/``, e.g. ``quickstart``) and overridden from the command
line with ``--set section.field=value`` (the value is parsed as YAML: ``--set ppo.lr=1e-4``,
``--set env.tasks=[reach,push]``).

Errors name the field: an unknown key, a wrong type, a value out of range or an inconsistent
combination raise :class:`ConfigError` with the dotted path and the bad value.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Union

import yaml

__all__ = [
    "ConfigError",
    "EnvConfig",
    "NetworkConfig",
    "PPOConfig",
    "ClusteringConfig",
    "RuntimeConfig",
    "ApiConfig",
    "EvalConfig",
    "Config",
    "load_config",
    "read_config_file",
    "resolve_config_path",
    "shipped_configs",
    "config_from_dict",
    "config_to_dict",
    "apply_overrides",
    "DEFAULT_THRESHOLDS",
    "describe",
    "reference",
]


#: URI schemes of ``runtime.storage`` (the filesystems pyarrow.fs opens by URI)
STORAGE_SCHEMES = ("file", "s3", "gs", "gcs", "hdfs", "abfs", "abfss")


class ConfigError(ValueError):
    """A configuration value is missing, unknown, mistyped or inconsistent."""


_HOST_LABEL = re.compile(r"^(?!-)[A-Za-z0-9-]{1,63}(?<!-)$")


def valid_host(host: str) -> bool:
    """Whether ``host`` is an IPv4/IPv6 address or a DNS host name (RFC 1123 labels) to bind or name."""
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        pass
    name = host[:-1] if host.endswith(".") else host
    return 0 < len(name) <= 253 and all(_HOST_LABEL.match(label) for label in name.split("."))


def _f(default: Any, doc: str, **kw: Any) -> Any:
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda d=default: type(d)(d), metadata={"doc": doc, **kw})
    return field(default=default, metadata={"doc": doc, **kw})


Metric = Literal["wasserstein", "euclidean", "mahalanobis"]
GroupName = Literal["D4", "C4", "D2", "C2", "D1", "trivial"]

#: Meta-World's own episode limit (``max_path_length``): an episode's steps times the action repeat.
METAWORLD_MAX_PATH_LENGTH = 500

#: Per-metric default thresholds d_eps, in units of the buffer's feature spread (clustering.feature_norm
#: "buffer"; the Mahalanobis distance is scale-free). Paper (raw trained features): W1 1.0, Euclidean
#: 0.3-0.7, Mahalanobis 3-7; these values sit in the measured gap between same-group and other-group
#: distances on the toy stream (docs/research/clustering.md).
DEFAULT_THRESHOLDS: dict[str, float] = {"wasserstein": 1.0, "euclidean": 0.8, "mahalanobis": 10.0}


@dataclass(frozen=True)
class EnvConfig:
    suite: Literal["toy", "metaworld"] = _f("toy", "Task family: pure-numpy toy tasks or Meta-World v3.")
    tasks: list[str] = _f(
        ["reach", "push", "avoid"],
        "Base task groups in the stream (toy: reach/push/avoid; metaworld: e.g. reach-v3).",
    )
    group: GroupName = _f("D4", "Symmetry group whose elements transform the base tasks.")
    image_size: int = _f(32, "Side of the square top-down image in pixels.", min=8, max=256)
    max_episode_steps: int = _f(50, "Episode length in agent steps (time-limit truncation).", min=1)
    action_repeat: int = _f(
        1,
        "Meta-World steps per agent step: each action is applied this many times (rewards summed, "
        "success if any), one image per agent step. Env steps count agent steps.",
        min=1,
        max=8,
    )
    success_bonus: float = _f(
        0.0,
        "Added to the reward of every agent step on which the task succeeds (metaworld suite). Meta-World's "
        "reward is nearly flat at the edge of success (Goal Reach: 97-99% of its maximum at 1.1-1.3 success "
        "radii), so a policy can stop just outside it at almost no cost; 0 keeps Meta-World's reward.",
        min=0.0,
    )
    success_bonus_once: bool = _f(
        False,
        "Pay env.success_bonus once per episode, on the first step that succeeds, instead of on every "
        "successful step: the edge of success becomes a step in the return without the return growing with "
        "the steps spent inside (Button Press's pressed button stays pressed).",
    )
    success_bonus_radius: float = _f(
        1.0,
        "Pay env.success_bonus only where the task's distance is within this fraction of its success radius "
        "(info target_ratio <= this): 1 pays it on every success; below 1 only on steps that go past the edge "
        "into the success region, so the greedy policy aims inside it rather than at its edge (Goal Reach's "
        "failures end at 1.0-1.1 radii).",
        gt=0.0,
        max=1.0,
    )
    episodes_per_task: int = _f(20, "Episodes before the stream switches to the next task.", min=1)
    held_out: int = _f(0, "Number of (group, g) pairs held out of training for generalization tests.", min=0)
    render_backend: Literal["auto", "egl", "osmesa", "numpy"] = _f(
        "auto",
        "Meta-World image renderer: numpy (MuJoCo geometry rasterized top-down, no OpenGL; what auto "
        "picks) or MuJoCo's GL renderer on the egl / osmesa platform (MUJOCO_GL must match).",
    )
    camera_shift: float = _f(0.0, "Camera xy shift dp in metres (robustness evaluation).", min=0.0)
    camera_shift_angle: float = _f(0.0, "Direction of the camera shift, degrees counter-clockwise from +x.")
    palette: Literal["task", "mono"] = _f(
        "task",
        "Object colours (metaworld suite): task = each task's objects in their own colours; mono = every object "
        "and marker of every task in one light grey on the grey table, so that only shape and layout tell the "
        "groups apart (docs/guide/tasks.md).",
    )

    def __post_init__(self) -> None:
        from .symmetry import get_group

        if self.suite == "metaworld" and not 32 <= self.image_size <= 128:
            raise ConfigError(f"env.image_size={self.image_size}: Meta-World images must be 32..128 px")
        if self.action_repeat > 1 and self.suite != "metaworld":
            raise ConfigError(f"env.action_repeat={self.action_repeat}: action repeat applies to the metaworld suite only")
        if not math.isfinite(self.success_bonus):
            raise ConfigError(f"env.success_bonus={self.success_bonus}: must be a finite number >= 0")
        if self.palette == "mono" and self.suite != "metaworld":
            raise ConfigError("env.palette=mono recolours Meta-World objects; it applies to the metaworld suite only")
        if self.success_bonus > 0 and self.suite != "metaworld":
            raise ConfigError(f"env.success_bonus={self.success_bonus}: the success bonus applies to the metaworld suite only")
        if self.success_bonus_once and self.success_bonus == 0:
            raise ConfigError("env.success_bonus_once=true pays env.success_bonus once; set env.success_bonus > 0 too")
        if not 0 < self.success_bonus_radius <= 1:  # NaN as well
            raise ConfigError(f"env.success_bonus_radius={self.success_bonus_radius}: must be a fraction in (0, 1]")
        if self.success_bonus_radius < 1 and self.success_bonus == 0:
            raise ConfigError(
                f"env.success_bonus_radius={self.success_bonus_radius} says where env.success_bonus is paid; "
                "set env.success_bonus > 0 too"
            )
        if self.suite == "metaworld" and self.max_episode_steps * self.action_repeat > METAWORLD_MAX_PATH_LENGTH:
            raise ConfigError(
                f"env.max_episode_steps={self.max_episode_steps} x env.action_repeat={self.action_repeat} = "
                f"{self.max_episode_steps * self.action_repeat} Meta-World steps per episode; Meta-World allows at "
                f"most {METAWORLD_MAX_PATH_LENGTH}"
            )
        trainable = len(self.tasks) * (len(get_group(self.group)) - 1)
        if self.held_out > trainable:
            raise ConfigError(
                f"env.held_out={self.held_out} exceeds {trainable}: every task group must keep at least one "
                f"trained (task, g) pair ({len(self.tasks)} tasks x {len(get_group(self.group))} elements of "
                f"{self.group})"
            )


@dataclass(frozen=True)
class NetworkConfig:
    kind: Literal["equivariant", "cnn"] = _f("equivariant", "Feature extractor: escnn equivariant or plain CNN.")
    group: GroupName = _f("D4", "Group the equivariant encoder is built for.")
    channels: list[int] = _f(
        [4, 8, 8, 16],
        "Regular fields per conv block; each block halves the image (CNN twin: channels scaled by cnn_width).",
    )
    hidden: int = _f(
        32, "Regular fields of the fused head layer; its group pooling gives the `hidden` invariant features.", min=1
    )
    space_to_depth: Literal[1, 2, 4] = _f(
        1,
        "Stem: fold each k x k pixel block into channels before the first block (lossless, exactly "
        "equivariant; every block then runs on a k times smaller map, about k^2 fewer FLOPs). 1: off.",
    )
    init_log_std: float = _f(-0.5, "Initial log standard deviation of the Gaussian policy.")
    action_mean: Literal["tanh", "linear"] = _f(
        "tanh",
        "The Gaussian's mean: tanh of the policy head's output, inside the action box [-1, 1] (tanh is odd, so "
        "it commutes with the D4 signed permutations of (dx, dy): equivariance stays exact), or linear: the "
        "head's output itself (older runs; its mean can drift far outside the box, where the env's clipping "
        "makes those entries' gradient pure noise: docs/research/learning.md).",
    )
    proprio_norm: bool = _f(
        False,
        "Feed (proprio - shift) * scale with the task family's fixed statistics (Meta-World: hand position in "
        "tenths of a metre about the table's centre, gripper opening to -1..1; docs/guide/models.md). Planar pairs "
        "take one scale and no shift, so equivariance stays exact. false: the raw proprio (older runs).",
    )
    critic: Literal["shared", "separate"] = _f(
        "shared",
        "shared: the value head reads the policy's trunk (one network); separate: the value comes from a second "
        "core of the same shape, so the value loss no longer moves the features the policy and the clustering "
        "read (about twice the network's compute; docs/guide/models.md).",
    )
    cnn_width: float | None = _f(
        None,
        "CNN twin channels = round(channels[i] * cnn_width); null: sqrt(|group|), a similar parameter count.",
        gt=0.0,
    )


@dataclass(frozen=True)
class PPOConfig:
    lr: float = _f(3e-4, "Adam learning rate.", gt=0.0)
    lr_schedule: Literal["constant", "linear"] = _f("constant", "Learning-rate schedule over updates.")
    gamma: float = _f(0.99, "Discount factor.", min=0.0, max=1.0)
    gae_lambda: float = _f(0.95, "GAE lambda.", min=0.0, max=1.0)
    clip_coef: float = _f(0.2, "PPO ratio clip epsilon.", gt=0.0)
    vf_clip_coef: float | None = _f(
        None,
        "Value clipping range (null: no value clipping, the default: with return normalisation it only slowed "
        "the critic, docs/research/learning.md).",
    )
    ent_coef: float = _f(0.0, "Entropy bonus coefficient.", min=0.0)
    ent_schedule: Literal["constant", "linear"] = _f(
        "constant",
        "Entropy-bonus schedule over updates: constant (ent_coef throughout) or linear (ent_coef at update 0 "
        "falling to 0 at ppo.total_updates, 0 after): exploration early, none once the group is learned.",
    )
    noise_beta: float = _f(
        0.0,
        "Colour of the training episodes' action noise: each episode draws its standard-normal noise with a "
        "1/f^beta power spectrum (covers_dist/ppo/noise.py), so every step is still N(mean, std) but the noise "
        "of consecutive steps points the same way for longer. 0: white, independent per step (the default); "
        "1: pink; 2: red. Evaluation's stochastic mode keeps white noise.",
        min=0.0,
        max=2.0,
    )
    noise_fraction: float = _f(
        1.0,
        "The fraction of training episodes sampled with the coloured noise (ppo.noise_beta, faded by "
        "ppo.noise_fade_success); the others get white noise. Spread evenly over the episode indices (0.5: "
        "every second episode), so a batch mixes both.",
        min=0.0,
        max=1.0,
    )
    noise_entries: Literal["all", "planar", "scalar"] = _f(
        "all",
        "Which action entries get the colour (ppo.noise_beta); the others keep white noise. all: every entry; "
        "planar: the table-plane pairs (x, y: the entries the group rotates and mirrors); scalar: the others "
        "(height, gripper). Chosen per kind, never per entry, so the noise stays invariant under the group.",
    )
    noise_fade_success: float | None = _f(
        None,
        "A policy's noise turns white as it succeeds: its colour is noise_beta * max(0, 1 - s / this), s its "
        "training success over the last 64 episodes it acted (covers_dist/ppo/noise.py, faded_beta), so a new "
        "policy searches with coloured noise and a policy that succeeds this often samples white noise. null: "
        "every policy keeps noise_beta.",
        gt=0.0,
        max=1.0,
    )
    vf_coef: float = _f(0.5, "Value loss coefficient.", min=0.0)
    epochs: int = _f(4, "Optimization epochs per update.", min=1)
    minibatch_size: int = _f(256, "Samples per minibatch.", min=1)
    max_grad_norm: float = _f(0.5, "Gradient-norm clip.", gt=0.0)
    bound_coef: float = _f(
        0.0,
        "Weight of a soft bound on the Gaussian's mean, sum_i relu(|mu_i| - 1.1)^2 (rl_games' bounds loss): keeps a "
        "linear mean (network.action_mean=linear) near the action box [-1, 1]; 0: off.",
        min=0.0,
    )
    target_kl: float | None = _f(None, "Stop the epochs early once approx-KL exceeds this (null: never).")
    kl_reference: Literal["behaviour", "update_start"] = _f(
        "behaviour",
        "What ppo.target_kl measures the policy's move from: behaviour = the policy that acted the batch (a "
        "pipelined batch is acted one update old, so a batch can stop at its first minibatch, before any step: "
        "docs/research/learning.md); update_start = the policy at the start of this update (one more forward pass).",
    )
    log_std_cap: float | None = _f(
        None,
        "A falling cap on the policy's learned log standard deviation: after each update every entry is clipped "
        "to at most a bound that falls linearly from the learner's starting value (network.init_log_std) at "
        "update 0 to this at ppo.total_updates, and stays there (the exploration noise shrinks on a schedule "
        "without an entropy term; docs/research/learning.md). null: the standard deviation is learned freely.",
    )
    weight_average: float | None = _f(
        None,
        "Decay d of an exponential moving average of the policy's weights, kept by its learner beside them and "
        "moved after every update (avg = d * avg + (1 - d) * weights; the parameters are the equivariant basis "
        "coefficients, so the average is exactly equivariant too). Training never acts with it: `bench learn` "
        "evaluates it, with the newest weights beside it on the same points (docs/research/learning.md, \"The average of "
        "the last weights\"). null: none kept.",
        gt=0.0,
        max=0.999,
    )
    norm_adv: bool = _f(True, "Normalize advantages per minibatch.")
    total_updates: int | None = _f(
        None,
        "Horizon of the linear learning-rate schedule and of ppo.log_std_cap, in updates of one policy; null: the "
        "run's length in updates, runtime.total_env_steps / (clustering.update_every * env.max_episode_steps) "
        "(Config.learner_ppo).",
        min=1,
    )
    reward_scale: float = _f(
        0.1,
        "Rewards are multiplied by this before GAE, so value targets stay O(1) (toy: about -0.5 per step; "
        "Meta-World: 0..10 per step, try 0.01).",
        gt=0.0,
    )
    reward_norm: Literal["none", "return"] = _f(
        "return",
        "return: rewards (after reward_scale) are divided by a running standard deviation of the discounted "
        "return, kept across updates in the learner's state, so value targets are O(1) on any reward scale "
        "(docs/research/learning.md); none: rewards times reward_scale only.",
    )
    precision: Literal["auto", "fp32", "bf16"] = _f(
        "auto",
        "Update arithmetic: bf16 autocast of the forward pass (fp32 weights, optimizer and loss) or fp32. "
        "auto: bf16 on a CUDA learner or a CPU with native bf16 (AVX-512 BF16 or AMX), else fp32 "
        "(emulated bf16 is several times slower). Rollout inference is always fp32.",
    )


@dataclass(frozen=True)
class ClusteringConfig:
    metric: Metric = _f("wasserstein", "Distance between initial-frame feature sets.")
    threshold: float | None = _f(None, "d_eps; null picks the metric's default (W1 1.0, Euclid 0.8, Mahal 10.0).")
    buffer_size: int = _f(128, "Initial observations kept per policy buffer B_i.", min=1)
    replacement: Literal["fifo", "reservoir"] = _f("reservoir", "How a full buffer admits new observations.")
    initial_frames: int = _f(1, "k: first frames of each episode used for clustering.", min=1)
    update_every: int = _f(8, "Nu: episodes per iteration (rolled out, assigned together, then one PPO update).", min=1)
    feature_source: Literal["joint", "own", "shared", "colors"] = _f(
        "joint",
        "joint = every policy's own invariant encoder output, unit length, side by side: one learned space "
        "for every comparison (docs/guide/clustering.md, 'Feature source and normalization'); own = each policy's own encoder for "
        "its own buffer (the paper's); shared = one frozen untrained encoder; colors = a fixed colour "
        "histogram of the frame (hand-designed, no learning; an ablation).",
    )
    max_policies: int = _f(64, "Bank size limit; when reached, the nearest policy is recalled.", min=1)
    feature_norm: Literal["buffer", "none", "l2"] = _f(
        "buffer",
        "Feature scaling before distances: buffer = O and B divided by B's mean pairwise feature distance "
        "(scale-free; d_eps in units of the buffer's spread), none = raw features, l2 = unit-length rows.",
    )
    rule: Literal["threshold", "calibrated"] = _f(
        "threshold",
        "Decision rule: threshold = recall the nearest policy when its distance <= d_eps, else a new one (the "
        "paper's); calibrated = per-policy exact permutation test of d(O, B_i) against d(O', B') for random splits "
        "of the pooled O and B_i into sets of sizes |O| and |B_i|, in the policy's current feature space; a new "
        "policy only when every policy rejects "
        "(docs/guide/clustering.md, 'Two decision rules').",
    )
    false_split_rate: float = _f(
        0.001,
        "Calibrated rule: a policy rejects O when its p-value is <= this (the chance, per policy and "
        "assignment, that a batch of the policy's own group is rejected); in (0, 0.5).",
        gt=0.0,
    )
    calibration_samples: int = _f(
        200,
        "Calibrated rule: least number of random splits of the pooled O and B_i per policy and assignment for "
        "the null distribution; max(this, ceil(1/false_split_rate) - 1) are drawn, stopped early once the "
        "decision is settled.",
        min=20,
    )
    merge_threshold: float | None = _f(
        None,
        "Healing: every merge_every assignments, a policy whose buffer lies within this W1 distance (the bank's "
        "features and normalization) of an older policy's buffer is merged into it (its frames, episodes and "
        "labels; its learner stops). null = never merge (docs/guide/clustering.md, 'A bank that heals').",
        gt=0.0,
    )
    merge_every: int = _f(8, "Healing: assignments between two merge checks.", min=1)
    tie_margin: float = _f(
        0.0,
        "A recall between near-equal candidates: among the policies that accept O with distances within "
        "d_min / (1 - tie_margin), the one assigned most often (the one that has trained) is chosen; 0 = the nearest.",
        min=0.0,
        max=0.9,
    )
    assign_at: Literal["iteration", "reset"] = _f(
        "iteration",
        "When a batch is assigned: iteration = after its episodes were rolled out with the current policy "
        "(the paper's Algorithm 1: after a task switch, episodes are acted by the previous group's policy); "
        "reset = from the episodes' first frames before they act, so every episode is acted by the policy "
        "it is assigned to (needs initial_frames = 1: the first frame does not depend on the policy).",
    )

    def __post_init__(self) -> None:
        if self.assign_at == "reset" and self.initial_frames != 1:
            raise ConfigError(
                f"clustering.assign_at=reset needs clustering.initial_frames=1 (got {self.initial_frames}): "
                "later frames depend on the policy that acts before the assignment"
            )
        if self.rule not in ("threshold", "calibrated"):
            raise ConfigError(f"clustering.rule: expected one of ['threshold', 'calibrated'], got {self.rule!r}")
        r = self.false_split_rate
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0.0 < r < 0.5:
            raise ConfigError(f"clustering.false_split_rate={r!r} must be in (0, 0.5)")
        n = self.calibration_samples
        if isinstance(n, bool) or not isinstance(n, int) or n < 20:
            raise ConfigError(f"clustering.calibration_samples={n!r} must be an integer >= 20")


@dataclass(frozen=True)
class RuntimeConfig:
    method: Literal["covers", "covers-gt", "covers-cnn", "equi", "cnn"] = _f("covers", "Method variant.")
    serial: bool = _f(False, "Run every component in one process (no Ray).")
    num_workers: int = _f(2, "Rollout worker actors.", min=1)
    envs_per_worker: int = _f(2, "Environments stepped together in each worker.", min=1)
    total_env_steps: int = _f(20000, "Stop after this many env steps.", min=1)
    num_cpus: int = _f(2, "CPUs for a locally started Ray instance.", min=1)
    num_gpus: float = _f(
        0.0, "GPUs per learner actor, fractions allowed (0.25: four learners share a GPU; 0: CPU learners).", min=0.0
    )
    check_fit: bool = _f(
        True,
        "Refuse at start a run whose actors can never all be placed on the Ray cluster's nodes (false: skip the "
        "check, e.g. when an autoscaler adds the nodes later).",
    )
    ray_address: str | None = _f(None, "Address of a running Ray cluster (null: start a local one).")
    run_dir: str = _f("runs/latest", "Directory for metrics, checkpoints and plots.")
    storage: str | None = _f(
        None,
        "Where the run's state lives for every process of it (live learner and clustering state, process records, "
        "copies of the checkpoints and logs): a local path or a pyarrow.fs URI (s3://bucket/prefix, gs://..., "
        "file://...). null: runtime.run_dir, which on a multi-node cluster must then be a disk every node mounts.",
    )
    checkpoint_every: int = _f(10, "Update steps between checkpoints.", min=1)
    storage_retry_s: float = _f(
        120.0,
        "Seconds an object store's failing reads and writes are retried (backoff from 0.25 s to 8 s, each retry "
        "logged) before the run stops cleanly at its last valid checkpoint.",
        gt=0.0,
    )
    lease_ttl_s: float = _f(
        60.0,
        "Seconds a driver's lease on the run's storage lives unrenewed (renewed every third of it): a second "
        "driver of the run is refused while it lives; one whose driver died is taken over after it.",
        gt=0.0,
    )
    torch_threads: int = _f(1, "torch intra-op threads per rollout worker and clustering process.", min=1)
    pipeline: bool = _f(
        True,
        "Overlap each iteration's sampling with the previous iteration's PPO update (sampling then uses "
        "weights one update old; PPO's ratio corrects for it). false: the strict sequential order of Algorithm 1.",
    )
    learner_num_cpus: float = _f(
        0.0, "CPUs reserved by each learner actor on Ray (0: none, it shares the workers' cores).", min=0.0
    )
    learners_per_process: int = _f(
        1,
        "Policies whose learners share one learner process on Ray: process k hosts policies k*n .. k*n+n-1, "
        "each learner built when its policy first needs it. Fewer processes (memory, process starts) at the "
        "price of one process's updates running one after another (a stream trains one group at a time). "
        "runtime.learner_num_cpus and runtime.num_gpus are then per process. 1: one process per policy.",
        min=1,
    )
    learner_ahead: bool = _f(
        True,
        "Start the next policy's learner actor before the bank creates that policy, so its start-up overlaps "
        "training (false: each learner starts when its policy appears; no idle learner holds CPUs or GPUs).",
    )
    learner_threads: int = _f(
        0,
        "torch intra-op threads per learner; 0 (auto): runtime.learner_num_cpus rounded up where the learner "
        "reserves cores, else 1 (it shares the cores with the rollout workers: on 2 cores a second thread made "
        "the pipelined loop slower, docs/research/runtime.md; on a CPU without native bf16, whose fp32 update outlasts "
        "sampling, 2 sped up `bench train` but slowed the demo, whose evaluation passes use the idle core: run F).",
        min=0,
    )
    actor_nice: int = _f(
        10,
        "Niceness of rollout worker and learner processes on Ray, so the HTTP service, the driver and the "
        "clustering actor get the CPU first when training saturates it (0..19; 0: equal priority).",
        min=0,
        max=19,
    )
    time_limit_minutes: float | None = _f(
        None,
        "Stop training after this many minutes of wall clock in the training loop (counted from the start or the "
        "resume, evaluation passes that run meanwhile included), then run the final evaluation pass and checkpoint "
        "as at total_env_steps (null: no limit).",
        gt=0.0,
    )
    log_every_s: float = _f(5.0, "Seconds between console progress lines.", gt=0.0)
    log_rotate_mb: float | None = _f(
        64.0,
        "Size in MiB at which metrics.jsonl and episodes.jsonl are rotated into gzip segments "
        "(NAME.<seq>.gz) and a TensorBoard event file is closed for a new one (null: never rotate).",
    )
    log_keep: int = _f(
        5,
        "Rotated segments kept per JSONL log (the oldest are deleted; 0: none), and closed TensorBoard "
        "event files kept (more while together they hold no more than log_keep x log_rotate_mb).",
        min=0,
    )

    def __post_init__(self) -> None:
        if self.storage is not None and not str(self.storage).strip():
            raise ConfigError("runtime.storage is empty: give a local path, a URI such as s3://bucket/prefix, or null")
        if self.storage is not None and "://" in self.storage:
            from .storage import redact_uri, uri_credentials

            scheme = self.storage.split("://", 1)[0]
            shown = redact_uri(self.storage.split("?", 1)[0])
            if scheme not in STORAGE_SCHEMES:
                raise ConfigError(
                    f"runtime.storage={shown!r}: unknown scheme {scheme!r}, "
                    f"expected a local path or one of {', '.join(s + '://' for s in STORAGE_SCHEMES)}"
                )
            found = uri_credentials(self.storage)
            if found:
                raise ConfigError(
                    f"runtime.storage={redact_uri(self.storage)!r} carries credentials ({', '.join(found)}), which "
                    "would be saved with the run's config and shown in its logs: give them in the environment "
                    "instead (AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY, GOOGLE_APPLICATION_CREDENTIALS, ...)"
                )
        mb = self.log_rotate_mb
        if mb is not None and (isinstance(mb, bool) or not isinstance(mb, (int, float)) or not mb > 0):
            raise ConfigError(f"runtime.log_rotate_mb={mb!r} must be > 0 (null: never rotate)")


@dataclass(frozen=True)
class ApiConfig:
    enabled: bool = _f(False, "Start the HTTP service next to training.")
    host: str = _f("127.0.0.1", "Bind address: an IPv4 or IPv6 address or a host name (loopback unless configured).")
    port: int = _f(8000, "TCP port.", min=0, max=65535)
    token: str | None = _f(
        None,
        "Bearer token required on every route but health checks; never written to config.yaml or checkpoints "
        "(prefer api.token_file or COVERS_API_TOKEN).",
    )
    token_file: str | None = _f(
        None, "File whose first line is the bearer token (used when api.token is not set; else COVERS_API_TOKEN)."
    )
    max_body_bytes: int = _f(8_000_000, "Largest accepted request body in bytes (larger: 413).", min=1)
    max_batch: int = _f(256, "Most observations in one POST /v1/assignments/what-if request.", min=1)
    refresh_s: float = _f(0.5, "Seconds between snapshots of the clustering state that the GET endpoints serve.", gt=0.0)
    request_timeout_s: float = _f(30.0, "Seconds to wait for the clustering service before answering 503.", gt=0.0)
    compute_concurrency: int = _f(
        2, "POST /v1/assignments/what-if and /v1/act calls in flight at once, PNG decoding included (others wait).",
        min=1,
    )
    max_connections: int = _f(
        64,
        "Connections (open or with a request in flight) at which the server answers new requests 503 at once "
        "(uvicorn's limit_concurrency: the connection that asks counts).",
        min=1,
    )
    allowed_hosts: list[str] | None = _f(
        None,
        "Host header names the server answers (others: 400), against DNS rebinding. null: with no token, the "
        "loopback names (localhost, 127.0.0.1, ::1) and api.host; with a token, any. ['*']: any.",
    )

    def __post_init__(self) -> None:
        bad = [h for h in self.allowed_hosts or [] if h != "*" and not valid_host(h)]
        if bad or self.allowed_hosts == []:
            raise ConfigError(f"api.allowed_hosts={self.allowed_hosts!r}: every entry must be a host name, an IP "
                              "address or '*' (null: the default)")  # fmt: skip
        if not valid_host(self.host):
            raise ConfigError(
                f"api.host={self.host!r} is not an IP address or a host name (e.g. 127.0.0.1, ::1, localhost, 0.0.0.0)"
            )


EvalMode = Literal["greedy", "stochastic"]
EvalSelection = Literal["agnostic", "oracle"]


@dataclass(frozen=True)
class EvalConfig:
    every_iterations: int = _f(
        0, "Evaluate every (task, g) every this many iterations during training, and at the end (0: off).", min=0
    )
    episodes: int = _f(4, "Episodes per (task, g) pair, chosen policy and mode (seeded apart from training).", min=1)
    modes: list[EvalMode] = _f(["greedy", "stochastic"], "Action modes: greedy (mean action) and/or stochastic.")
    selections: list[EvalSelection] = _f(
        ["agnostic", "oracle"],
        "How the policy is chosen: agnostic (the bank's rule on the episodes' first frames, bank unchanged) "
        "and/or oracle (the policy that trained on the pair's true group).",
    )
    tasks: list[str] | None = _f(None, "Base tasks to evaluate (null: all of env.tasks).")
    stop_at: float | None = _f(
        None,
        "Stop training once a group's greedy success on its worst (task, g) pair is >= this at eval.held "
        "consecutive passes (eval.stop_groups says whether one group or every evaluated group must), then run the "
        "final pass and checkpoint (null: never; needs eval.every_iterations > 0 and greedy in eval.modes).",
        gt=0.0,
        max=1.0,
    )
    stop_groups: Literal["any", "all"] = _f(
        "all", "For eval.stop_at: stop when any evaluated group meets it, or only when all of them do."
    )
    held: int = _f(2, "Consecutive passes at which a group must meet eval.stop_at.", min=1)
    workers: int = _f(1, "Ray evaluation actors (serial runs evaluate in the driver's process).", min=1)
    num_cpus: float = _f(
        0.0,
        "CPUs reserved per evaluation actor (0: none, so evaluation shares the training workers' cores "
        "instead of waiting for free ones).",
        min=0.0,
    )


@dataclass(frozen=True)
class Config:
    name: str = _f("covers", "Run name.")
    seed: int = _f(0, "Global random seed.", min=0)
    env: EnvConfig = field(default_factory=EnvConfig, metadata={"doc": "Tasks and rendering."})
    network: NetworkConfig = field(default_factory=NetworkConfig, metadata={"doc": "Actor-critic network."})
    ppo: PPOConfig = field(default_factory=PPOConfig, metadata={"doc": "PPO learner."})
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig, metadata={"doc": "Policy assignment."})
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig, metadata={"doc": "Actors and the loop."})
    api: ApiConfig = field(default_factory=ApiConfig, metadata={"doc": "HTTP service."})
    eval: EvalConfig = field(default_factory=EvalConfig, metadata={"doc": "Evaluation of every (task, g)."})

    def __post_init__(self) -> None:
        _validate_cross_fields(self)

    @property
    def threshold(self) -> float:
        """The effective d_eps (the configured one, or the metric's default)."""
        t = self.clustering.threshold
        return DEFAULT_THRESHOLDS[self.clustering.metric] if t is None else t

    @property
    def steps_per_update(self) -> int:
        """Env steps of one iteration and its PPO update: ``update_every`` episodes of ``max_episode_steps``."""
        return self.clustering.update_every * self.env.max_episode_steps

    @property
    def updates_per_run(self) -> int:
        """PPO updates in ``runtime.total_env_steps``, at least 1."""
        return max(1, -(-self.runtime.total_env_steps // self.steps_per_update))

    @property
    def learner_ppo(self) -> PPOConfig:
        """``ppo`` as a learner uses it: a null ``total_updates`` is the run's length in updates."""
        if self.ppo.total_updates is not None:
            return self.ppo
        return dataclasses.replace(self.ppo, total_updates=self.updates_per_run)


#: Suites whose observation layout carries fixed proprio statistics (``network.proprio_norm``).
SUITES_WITH_PROPRIO_STATS = ("metaworld",)


def _validate_cross_fields(cfg: Config) -> None:
    from .symmetry import get_group

    if not cfg.env.tasks:
        raise ConfigError("env.tasks: at least one task is needed")
    if len(set(cfg.env.tasks)) != len(cfg.env.tasks):
        raise ConfigError(f"env.tasks: duplicate task names in {cfg.env.tasks}")
    if cfg.env.suite == "toy" and cfg.env.image_size % 2:
        raise ConfigError(f"env.image_size={cfg.env.image_size}: the toy suite needs an even size")
    env_group = {g for g in get_group(cfg.env.group)}
    net_group = {g for g in get_group(cfg.network.group)}
    if cfg.network.kind == "equivariant" and not env_group <= net_group:
        raise ConfigError(
            f"network.group={cfg.network.group} does not contain env.group={cfg.env.group}: "
            "the policy could not treat every transformed task as equivalent"
        )
    if any(c < 1 for c in cfg.network.channels):
        raise ConfigError(f"network.channels={cfg.network.channels}: every entry must be >= 1")
    if cfg.network.proprio_norm and cfg.env.suite not in SUITES_WITH_PROPRIO_STATS:
        raise ConfigError(
            f"network.proprio_norm=true: env.suite={cfg.env.suite} has no proprio statistics "
            f"(suites that have them: {list(SUITES_WITH_PROPRIO_STATS)})"
        )
    from .sizes import block_sizes  # plain arithmetic: importing it pulls in no torch

    try:
        block_sizes(cfg.env.image_size, len(cfg.network.channels), cfg.network.space_to_depth)
    except ValueError as exc:
        raise ConfigError(f"env.image_size / network.channels / network.space_to_depth: {exc}") from None
    if cfg.clustering.threshold is not None and cfg.clustering.threshold <= 0:
        raise ConfigError(f"clustering.threshold={cfg.clustering.threshold} must be > 0")
    if cfg.runtime.method in ("covers-cnn", "cnn") and cfg.network.kind != "cnn":
        raise ConfigError(f"runtime.method={cfg.runtime.method} needs network.kind=cnn, got {cfg.network.kind}")
    if cfg.runtime.method in ("covers", "covers-gt", "equi") and cfg.network.kind != "equivariant":
        raise ConfigError(
            f"runtime.method={cfg.runtime.method} needs network.kind=equivariant, got {cfg.network.kind}"
        )
    steps_per_update = cfg.steps_per_update
    if cfg.ppo.minibatch_size > steps_per_update:
        raise ConfigError(
            f"ppo.minibatch_size={cfg.ppo.minibatch_size} exceeds the env steps of one update "
            f"(clustering.update_every * env.max_episode_steps = {steps_per_update})"
        )
    if cfg.eval.tasks is not None:
        unknown = [t for t in cfg.eval.tasks if t not in cfg.env.tasks]
        if unknown or not cfg.eval.tasks:
            raise ConfigError(f"eval.tasks={cfg.eval.tasks}: every entry must be one of env.tasks={cfg.env.tasks}")
    if not cfg.eval.modes or not cfg.eval.selections:
        raise ConfigError(f"eval.modes={cfg.eval.modes} and eval.selections={cfg.eval.selections} must not be empty")
    if cfg.eval.stop_at is not None and (cfg.eval.every_iterations == 0 or "greedy" not in cfg.eval.modes):
        raise ConfigError(
            f"eval.stop_at={cfg.eval.stop_at} needs periodic greedy passes: eval.every_iterations > 0 (got "
            f"{cfg.eval.every_iterations}) and 'greedy' in eval.modes (got {cfg.eval.modes})"
        )
    if not cfg.runtime.serial and cfg.runtime.ray_address is None and cfg.runtime.num_workers > 64:
        raise ConfigError(f"runtime.num_workers={cfg.runtime.num_workers} is too many for a local Ray instance")


# ---- conversion ------------------------------------------------------------------------------
def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return " | ".join(repr(a) for a in typing.get_args(tp))
    if origin in (Union, types.UnionType):
        return " | ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is list:
        return f"list[{_type_name(typing.get_args(tp)[0])}]"
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        given = [a for a in args if a is not type(None)]
        if len(given) == 1:  # ``X | None``: X's own message names what is wrong
            return _coerce(value, given[0], path)
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, path)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(f"{path}: expected {_type_name(tp)}, got {value!r}")
    if origin is Literal:
        choices = typing.get_args(tp)
        if value not in choices:
            raise ConfigError(f"{path}: expected one of {list(choices)}, got {value!r}")
        return value
    if origin is list:
        (item,) = typing.get_args(tp)
        if isinstance(value, tuple):
            value = list(value)
        if not isinstance(value, list):
            raise ConfigError(f"{path}: expected a list of {_type_name(item)}, got {value!r}")
        return [_coerce(v, item, f"{path}[{i}]") for i, v in enumerate(value)]
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str):  # YAML 1.1 reads "1e-4" (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                raise ConfigError(f"{path}: expected a number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{path}: expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, path)
    raise ConfigError(f"{path}: unsupported field type {tp!r}")  # pragma: no cover


def _check_range(value: Any, meta: typing.Mapping[str, Any], path: str) -> None:
    if value is None or isinstance(value, (list, str, bool)):
        return
    if "min" in meta and value < meta["min"]:
        raise ConfigError(f"{path}={value!r} must be >= {meta['min']}")
    if "max" in meta and value > meta["max"]:
        raise ConfigError(f"{path}={value!r} must be <= {meta['max']}")
    if "gt" in meta and value <= meta["gt"]:
        raise ConfigError(f"{path}={value!r} must be > {meta['gt']}")


def _build(cls: type, data: Any, path: str) -> Any:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path or 'config'}: expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        where = f"{path}." if path else ""
        raise ConfigError(
            f"unknown config key(s) {[where + str(u) for u in unknown]}; "
            f"valid keys{' in ' + path if path else ''}: {sorted(fields)}"
        )
    kwargs = {}
    for name, value in data.items():
        sub = f"{path}.{name}" if path else name
        kwargs[name] = _coerce(value, hints[name], sub)
        _check_range(kwargs[name], fields[name].metadata, sub)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:  # pragma: no cover - defensive
        raise ConfigError(f"{path or 'config'}: {e}") from e


def config_from_dict(data: dict[str, Any]) -> Config:
    """Build and validate a :class:`Config` from a nested mapping."""
    return _build(Config, data, "")


#: Fields that hold secrets: :func:`config_to_dict` leaves them out (null), so they never reach a
#: run's config.yaml, its checkpoints, the storage's copies or an actor's answer.
SECRET_FIELDS = (("api", "token"),)


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """The config as a plain nested dict (YAML/JSON friendly), secrets (:data:`SECRET_FIELDS`) null."""
    data = dataclasses.asdict(cfg)
    for section, key in SECRET_FIELDS:
        if isinstance(data.get(section), dict) and key in data[section]:
            data[section][key] = None
    return data


def apply_overrides(data: dict[str, Any], overrides: list[str] | None) -> dict[str, Any]:
    """Apply ``section.field=value`` overrides (values parsed as YAML) to a nested dict."""
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.field=value")
        key, raw = item.split("=", 1)
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"override {item!r} has an empty key part")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as e:
            raise ConfigError(f"override {item!r}: value is not valid YAML ({e})") from e
        node = data
        for p in parts[:-1]:
            child = node.get(p)
            if child is None:
                child = node[p] = {}
            elif not isinstance(child, dict):
                raise ConfigError(f"override {item!r}: {p} is not a section")
            else:
                child = node[p] = dict(child)
            node = child
        node[parts[-1]] = value
    return data


def _read_yaml(path: str | Path) -> dict[str, Any]:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {str(p)!r} does not exist")
    try:
        loaded = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"config file {str(p)!r} is not valid YAML: {e}") from e
    if loaded is None:
        loaded = {}
    if not isinstance(loaded, dict):
        raise ConfigError(f"config file {str(p)!r} must hold a mapping at the top level")
    return loaded


#: The configs shipped inside the package (``covers_dist/configs/*.yaml``; the repository's
#: top-level ``configs`` points there).
SHIPPED_CONFIG_DIR = Path(__file__).resolve().parent / "configs"


def shipped_configs() -> dict[str, Path]:
    """The shipped configs by name (file name without ``.yaml``), sorted."""
    return {p.stem: p for p in sorted(SHIPPED_CONFIG_DIR.glob("*.yaml"))}


def _shipped_path(path: str | Path) -> Path | None:
    """The shipped config a bare name (``quickstart``, ``quickstart.yaml``) or its repository path
    (``configs/quickstart.yaml``) names, else None."""
    p = Path(path)
    name = p.name[: -len(".yaml")] if p.name.endswith(".yaml") else p.name
    if len(p.parts) == 1 or (not p.is_absolute() and p.parent == Path("configs")):
        return shipped_configs().get(name)
    return None


def resolve_config_path(path: str | Path) -> Path:
    """The YAML file a ``--config`` value names.

    An existing file is used as given. Otherwise a bare name (``quickstart`` or ``quickstart.yaml``)
    or the repository path of a shipped config (``configs/quickstart.yaml``) names the file shipped
    in the package, so it resolves from any working directory. Anything else raises
    :class:`ConfigError` listing the shipped names.
    """
    p = Path(path)
    if p.is_file():
        return p
    shipped = _shipped_path(p)
    if shipped is not None:
        return shipped
    names = ", ".join(shipped_configs()) or "none"
    if len(p.parts) == 1:
        raise ConfigError(f"config {str(path)!r} does not exist: no such file and no shipped config of that name "
                          f"(shipped: {names})")
    raise ConfigError(f"config file {str(p)!r} does not exist (shipped configs, usable by name: {names})")


#: The top-level key by which a config file builds on another: ``base: stream_cpu`` takes that file's
#: values and lets this file's replace them field by field (a list is replaced whole).
BASE_KEY = "base"


def _merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    """``top`` over ``base``: sections merged field by field, any other value replaced."""
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _resolve_base(name: Any, owner: Path) -> Path:
    """The file a ``base:`` value in ``owner`` names: a file beside ``owner`` first (or an absolute
    path), then a shipped config (``stream_cpu``, ``stream_cpu.yaml`` or ``configs/stream_cpu.yaml``).
    Never a file of the working directory: the same config means the same thing from anywhere."""
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(f"config file {str(owner)!r}: {BASE_KEY} must name another config file, got {name!r}")
    for candidate in (owner.parent / name, owner.parent / f"{name}.yaml"):  # an absolute name stays as it is
        if candidate.is_file():
            return candidate
    shipped = _shipped_path(name)
    if shipped is not None:
        return shipped
    raise ConfigError(
        f"config file {str(owner)!r}: its {BASE_KEY} {name!r} was not found: no such file beside it "
        f"({str(owner.parent)!r}) and no shipped config of that name (shipped: {', '.join(shipped_configs()) or 'none'})"
    )


def read_config_file(path: Path, _chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A config file's values with its ``base:`` chain applied (the file's own values win)."""
    data = _read_yaml(path)
    if BASE_KEY not in data:
        return data
    chain = (*_chain, path.resolve())
    base_path = _resolve_base(data.pop(BASE_KEY), path)
    if base_path.resolve() in chain:
        names = " -> ".join(str(p) for p in (*chain, base_path.resolve()))
        raise ConfigError(f"config file {str(path)!r}: its {BASE_KEY} chain loops ({names})")
    return _merge(read_config_file(base_path, chain), data)


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Load a YAML config (or the defaults when ``path`` is None) and apply overrides.

    ``path`` is a file or the name of a shipped config (:func:`resolve_config_path`); a file with a
    top-level ``base:`` builds on the config it names (:func:`read_config_file`).
    """
    data: dict[str, Any] = {} if path is None else read_config_file(resolve_config_path(path))
    return config_from_dict(apply_overrides(data, overrides))


#: Fields added after runs were first saved, with the value such a run used: a run's config.yaml
#: holds every field of its day, so one it lacks predates the field (and today's default would
#: change what the run's checkpoints do).
SAVED_RUN_DEFAULTS: dict[tuple[str, str], Any] = {("network", "action_mean"): "linear"}


def load_run_config(path: str | Path) -> Config:
    """A run's saved config.yaml; fields it predates take :data:`SAVED_RUN_DEFAULTS`."""
    data = _read_yaml(path)
    for (section, key), value in SAVED_RUN_DEFAULTS.items():
        part = data.get(section)
        if isinstance(part, dict) and key not in part:
            part[key] = value
    return config_from_dict(data)


def describe(cls: type = Config, prefix: str = "") -> list[tuple[str, str, Any, str]]:
    """(dotted name, type, default, doc) for every field, for ``covers-dist config --describe``."""
    return [(r["name"], r["type"], r["default"], r["doc"]) for r in reference(cls, prefix)]


def reference(cls: type = Config, prefix: str = "") -> list[dict[str, Any]]:
    """Every field as ``{"name", "type", "default", "range", "doc"}`` (``range``: the bounds that
    loading checks, e.g. ``>= 1``; "" for none), in declaration order (docs/guide/configuration.md)."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        name = prefix + f.name
        if dataclasses.is_dataclass(tp):
            out.extend(reference(tp, name + "."))
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        bounds = [f"{op} {f.metadata[key]}" for key, op in (("min", ">="), ("gt", ">"), ("max", "<=")) if key in f.metadata]
        out.append({"name": name, "type": _type_name(tp), "default": default, "range": ", ".join(bounds),
                    "doc": f.metadata.get("doc", "")})  # fmt: skip
    return out
