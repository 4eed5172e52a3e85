"""The policy bank: one entry per policy (id, buffer of initial observations, counters, history).

:class:`PolicyBank` is plain Python (numpy, POT, scikit-learn): the clustering actor hosts one,
serial code and tests call it directly. It never builds networks; it reads features through a
:data:`~covers_dist.clustering.features.FeatureFn` and tells the caller, through each
:class:`~covers_dist.clustering.assignment.AssignmentRecord`, which policy to train next and
whether a fresh one must be made.

Episodes: an observation batch ``O`` holds the first ``k = initial_frames`` frames of each of
``E`` episodes (``n = E * k`` frames, episode by episode). Episodes carry indices (given by the
caller, or numbered by the bank from 0); their true group ids, when given, feed the metrics only.

Decision rules (``rule``): ``threshold`` (the paper's fixed ``d_eps``) or ``calibrated`` (a
per-policy permutation test, :meth:`PolicyBank.calibrated_distances`; docs/guide/clustering.md, "Two
decision rules").
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from .assignment import RULES, AssignmentRecord, decide, decide_calibrated
from .calibration import max_draws, permutation_test, splits_suffice
from .buffer import REPLACEMENT_RULES, ObservationBuffer, check_obs
from .distances import get_distance
from .features import FEATURE_NORMS, FeatureFn, check_features, normalize_pair
from .metrics import table_metrics
from .policy_entry import PolicyEntry, batch_group, check_int

__all__ = ["PolicyBank", "MODES"]

MODES: tuple[str, ...] = ("distance", "ground_truth")

#: Below this many buffer frames (or with too few distinct splits of ``O`` and ``B_i`` pooled, see
#: :func:`~covers_dist.clustering.calibration.splits_suffice`) the calibrated rule has no
#: meaningful null distribution and the threshold decides for that policy.
MIN_CALIBRATION_BUFFER = 8

#: A policy is considered for a merge (:meth:`PolicyBank.heal`) once its buffer holds this many frames.
MIN_MERGE_FRAMES = 16

_CALIBRATION_KEY = 0xCA1B  # spawn key of the calibration generator (buffers use entropy [seed, policy id])


@dataclass
class Calibration:
    """Output of :meth:`PolicyBank.calibrated_distances`.

    ``accepted[i]`` is what the decision rule reads: False for a policy that was not examined
    (farther than one that accepted), whose entry in ``tests`` says ``tested: False`` and
    ``accepted: None``. ``tests[i]``: ``tested`` (a permutation test ran), ``draws``,
    ``exceedances`` and ``p_value`` (None without a test), ``decided_by`` (``"permutation"``,
    ``"threshold"`` for a pool too small for the test, None when not examined) and ``accepted``
    (True / False, None when not examined)."""

    distances: dict[int, float]
    p_values: dict[int, float | None]
    accepted: dict[int, bool]
    draws: dict[int, int]
    max_draws: int = 0
    tests: dict[int, dict[str, Any]] = field(default_factory=dict)

    def record_info(self, rate: float, samples: int) -> dict[str, Any]:
        return {
            "false_split_rate": rate,
            "samples": samples,
            "test": "pooled_permutation",
            "max_draws": self.max_draws,
            "draws": {str(k): v for k, v in sorted(self.draws.items())},
            "fallback": sorted(k for k, t in self.tests.items() if t["decided_by"] == "threshold"),
            "accepted": sorted(k for k, t in self.tests.items() if t["accepted"]),
            "policies": {str(k): dict(t) for k, t in sorted(self.tests.items())},
        }


def calibration_generator(seed: int) -> np.random.Generator:
    """The bank's generator for the calibrated rule's random subsets."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(_CALIBRATION_KEY,))))


class PolicyBank:
    """Policies, their buffers ``B_i``, the assignment rule, the history and the metrics."""

    def __init__(
        self,
        feature_fn: FeatureFn | None = None,
        *,
        metric: str = "wasserstein",
        threshold: float = 1.0,
        buffer_size: int = 128,
        replacement: str = "reservoir",
        max_policies: int = 64,
        initial_frames: int = 1,
        feature_norm: str = "buffer",
        mode: str = "distance",
        seed: int = 0,
        rule: str = "threshold",
        false_split_rate: float = 0.001,
        calibration_samples: int = 200,
        merge_threshold: float | None = None,
        merge_every: int = 8,
        tie_margin: float = 0.0,
    ) -> None:
        get_distance(metric)  # validates the name
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not threshold > 0:
            raise ValueError(f"threshold must be a number > 0, got {threshold!r}")
        if replacement not in REPLACEMENT_RULES:
            raise ValueError(f"replacement must be one of {list(REPLACEMENT_RULES)}, got {replacement!r}")
        if feature_norm not in FEATURE_NORMS:
            raise ValueError(f"feature_norm must be one of {list(FEATURE_NORMS)}, got {feature_norm!r}")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {list(MODES)}, got {mode!r}")
        if rule not in RULES:
            raise ValueError(f"rule must be one of {list(RULES)}, got {rule!r}")
        r = false_split_rate
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0.0 < r < 0.5:
            raise ValueError(f"false_split_rate must be a number in (0, 0.5), got {r!r}")
        if feature_fn is not None and not callable(feature_fn):
            raise TypeError(f"feature_fn must be callable, got {type(feature_fn).__name__}")
        if merge_threshold is not None and (
            isinstance(merge_threshold, bool) or not isinstance(merge_threshold, (int, float)) or not merge_threshold > 0
        ):
            raise ValueError(f"merge_threshold must be a number > 0 or None, got {merge_threshold!r}")
        if isinstance(tie_margin, bool) or not isinstance(tie_margin, (int, float)) or not 0.0 <= tie_margin < 1.0:
            raise ValueError(f"tie_margin must be a number in [0, 1), got {tie_margin!r}")
        self.feature_fn = feature_fn
        self.metric = metric
        self.threshold = float(threshold)
        self.buffer_size = check_int("buffer_size", buffer_size, 1)
        self.replacement = replacement
        self.max_policies = check_int("max_policies", max_policies, 1)
        self.initial_frames = check_int("initial_frames", initial_frames, 1)
        self.feature_norm = feature_norm
        self.mode = mode
        self.seed = check_int("seed", seed, 0)
        self.rule = rule
        self.false_split_rate = float(false_split_rate)
        self.calibration_samples = check_int("calibration_samples", calibration_samples, 20)
        self.calibration_rng = calibration_generator(self.seed)
        self.merge_threshold = None if merge_threshold is None else float(merge_threshold)
        self.merge_every = check_int("merge_every", merge_every, 1)
        self.tie_margin = float(tie_margin)
        self.entries: dict[int, PolicyEntry] = {}
        self.retired: dict[int, PolicyEntry] = {}  # policies merged into another (never chosen again)
        self.merges: list[dict[str, Any]] = []  # one record per merge, in order
        self.history: list[AssignmentRecord] = []
        self.current_policy_id: int | None = None
        self.episode_policy: dict[int, int] = {}  # episode index -> policy id (assigned episodes)
        self.labels: dict[int, tuple[int, int]] = {}  # episode index -> (policy id, true group id)
        #: (policy id, true group id) -> labelled episodes: the metrics in time that does not grow
        #: with the run (kept with ``labels``; :meth:`rebuild_label_table` after replacing them)
        self.label_table: Counter[tuple[int, int]] = Counter()
        self.group_policy: dict[int, int] = {}  # ground-truth mode: group id -> policy id
        self.next_episode = 0
        if metric == "wasserstein":
            from .._imports import import_lightly

            import_lightly("ot")  # POT's first import costs about a second: pay it here, not in an assignment

    @classmethod
    def from_config(cls, cfg: Any, feature_fn: FeatureFn | None = None, mode: str | None = None) -> "PolicyBank":
        """Build from a :class:`covers_dist.config.Config` (``runtime.method == "covers-gt"`` picks
        ground-truth mode unless ``mode`` is given)."""
        c = cfg.clustering
        if mode is None:
            mode = "ground_truth" if cfg.runtime.method == "covers-gt" else "distance"
        return cls(
            feature_fn,
            metric=c.metric,
            threshold=cfg.threshold,
            buffer_size=c.buffer_size,
            replacement=c.replacement,
            max_policies=c.max_policies,
            initial_frames=c.initial_frames,
            feature_norm=c.feature_norm,
            mode=mode,
            seed=cfg.seed,
            rule=c.rule,
            false_split_rate=c.false_split_rate,
            calibration_samples=c.calibration_samples,
            merge_threshold=c.merge_threshold,
            merge_every=c.merge_every,
            tie_margin=c.tie_margin,
        )

    # ---- queries --------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.entries)

    @property
    def policy_ids(self) -> list[int]:
        return sorted(self.entries)

    def _features(self, policy_id: int, obs: dict[str, np.ndarray], n: int) -> np.ndarray:
        if self.feature_fn is None:
            raise ValueError("this bank has no feature_fn: pass one to PolicyBank(...) or set_feature_fn()")
        return check_features(self.feature_fn(policy_id, obs), n, policy_id)

    def set_feature_fn(self, feature_fn: FeatureFn | None) -> None:
        """Replace the feature source (e.g. after restoring a bank from a checkpoint)."""
        if feature_fn is not None and not callable(feature_fn):
            raise TypeError(f"feature_fn must be callable, got {type(feature_fn).__name__}")
        self.feature_fn = feature_fn

    def distances(self, obs: dict[str, np.ndarray], policies: Sequence[int] | None = None) -> dict[int, float]:
        """``d_i`` between ``obs`` and every policy's buffer (or those in ``policies``), in each
        policy's feature space."""
        distance = get_distance(self.metric)
        pairs = self._feature_pairs(obs, policies)
        return {pid: distance(*normalize_pair(f_o, f_b, self.feature_norm)) for pid, f_o, f_b in pairs}

    def _compared(self, policies: Sequence[int] | None) -> list[int]:
        """The policy ids an assignment compares with: all, or those of ``policies`` in the bank."""
        if policies is None:
            return self.policy_ids
        keep = {int(p) for p in policies}
        ids = [pid for pid in self.policy_ids if pid in keep]
        if self.entries and not ids:
            raise LookupError(f"none of the policies {sorted(keep)} is in the bank ({self.policy_ids})")
        return ids

    def _feature_pairs(
        self, obs: dict[str, np.ndarray], policies: Sequence[int] | None = None
    ) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """(policy id, raw features of ``obs``, raw features of ``B_i``) for every compared policy."""
        n = check_obs(obs)
        out: list[tuple[int, np.ndarray, np.ndarray]] = []
        ids = self._compared(policies)
        shared = getattr(self.feature_fn, "shared", False)
        f_obs = self._features(ids[0], obs, n) if shared and ids else None
        for pid in ids:
            buf = self.entries[pid].buffer.observations()
            if f_obs is not None:
                f_o, f_b = f_obs, self._features(pid, buf, len(buf["image"]))
            else:  # one encoder pass over O and B_i together
                both = {k: np.concatenate([obs[k], buf[k]]) for k in ("image", "proprio")}
                f = self._features(pid, both, n + len(buf["image"]))
                f_o, f_b = f[:n], f[n:]
            out.append((pid, f_o, f_b))
        return out

    def calibrated_distances(
        self, obs: dict[str, np.ndarray], rng: np.random.Generator, policies: Sequence[int] | None = None
    ) -> Calibration:
        """The calibrated rule's per-policy test (draws from ``rng``).

        For policy ``i`` with ``m = |O|`` and ``n = |B_i|``: the observed ``d(O, B_i)`` (the bank's
        metric and feature normalization, features from one encoder pass over ``O`` and ``B_i``)
        is compared with ``d(O*, B*)`` for random splits of ``O`` and ``B_i`` pooled into ``m`` and
        ``n`` vectors, in that same feature space (an exact permutation test,
        :func:`~covers_dist.clustering.calibration.permutation_test`): ``p_i = (1 + #{null >=
        observed}) / (1 + draws)``, and ``i`` accepts unless the test with all ``N =
        max(calibration_samples, ceil(1 / rate) - 1)`` draws has ``p_i <= false_split_rate``
        (draws stop once acceptance is settled). Policies are examined nearest first, and only
        until one accepts: the decision rule recalls the nearest accepting policy, so farther ones
        are not tested (recorded as ``tested: False``, never as accepted). With ``n <``
        :data:`MIN_CALIBRATION_BUFFER` or too few distinct splits of the pool
        (:func:`~covers_dist.clustering.calibration.splits_suffice`) the threshold decides for
        ``i`` (p-value None, ``decided_by: "threshold"``).
        """
        distance = get_distance(self.metric)
        norm, rate = self.feature_norm, self.false_split_rate
        full = max_draws(rate, self.calibration_samples)  # 1 / (1 + full) <= rate
        pairs = self._feature_pairs(obs, policies)
        observed = {pid: distance(*normalize_pair(f_o, f_b, norm)) for pid, f_o, f_b in pairs}
        cal = Calibration(distances=observed, p_values={}, accepted={}, draws={}, max_draws=full)
        decided = False
        reach = math.inf  # after the first acceptance: farther policies within the tie margin are tested too
        for pid, f_o, f_b in sorted(pairs, key=lambda t: (observed[t[0]], t[0])):
            d_obs, m, n = observed[pid], len(f_o), len(f_b)
            if decided and d_obs > reach:  # a nearer policy accepted: this one cannot change the decision
                test = {"tested": False, "draws": 0, "exceedances": None, "p_value": None,
                        "decided_by": None, "accepted": None}
            elif n < MIN_CALIBRATION_BUFFER or not splits_suffice(m, n, full):
                test = {"tested": False, "draws": 0, "exceedances": None, "p_value": None,
                        "decided_by": "threshold", "accepted": bool(d_obs <= self.threshold)}
            else:
                res = permutation_test(f_o, f_b, self.metric, norm, rate, full, rng)
                test = {"tested": True, "draws": res.draws, "exceedances": res.exceedances,
                        "p_value": res.p_value, "decided_by": "permutation", "accepted": res.accepted}
            cal.tests[pid] = test
            cal.p_values[pid], cal.draws[pid] = test["p_value"], test["draws"]
            cal.accepted[pid] = bool(test["accepted"])
            if cal.accepted[pid] and not decided:
                decided, reach = True, d_obs / (1.0 - self.tie_margin) if self.tie_margin else d_obs
        return cal

    # ---- the assignment step ----------------------------------------------------------------------
    def _episodes(
        self, n: int, episode_indices: Sequence[int] | None, group_ids: int | Sequence[int] | None, strict: bool
    ) -> tuple[list[int], list[int] | None]:
        if episode_indices is None:
            if n % self.initial_frames and strict:
                raise ValueError(f"obs holds {n} frames, not a multiple of initial_frames={self.initial_frames}")
            count = max(n // self.initial_frames, 1)
            episodes = list(range(self.next_episode, self.next_episode + count))
        else:
            episodes = [check_int("episode index", e, 0) for e in episode_indices]
            if not episodes or n % len(episodes):
                raise ValueError(f"obs holds {n} frames, which cannot be split evenly over {len(episodes)} episodes")
            if len(set(episodes)) != len(episodes):
                raise ValueError(f"episode_indices has duplicates: {episodes}")
            seen = [e for e in episodes if e in self.episode_policy or e in self.labels]
            if seen:
                raise ValueError(f"episode indices {seen} were already assigned")
        if group_ids is None:
            return episodes, None
        groups = [group_ids] * len(episodes) if isinstance(group_ids, (int, np.integer)) else list(group_ids)
        if len(groups) != len(episodes):
            raise ValueError(f"group_ids has {len(groups)} entries for {len(episodes)} episodes")
        return episodes, [check_int("group id", g, 0) for g in groups]

    def _plan(
        self,
        obs: dict[str, np.ndarray],
        episode_indices: Sequence[int] | None,
        group_ids: Any,
        strict: bool = True,
        rng: np.random.Generator | None = None,
        policies: Sequence[int] | None = None,
    ) -> tuple[AssignmentRecord, float]:
        t0 = time.perf_counter()
        n = check_obs(obs)
        if self.entries:  # every buffer holds frames of one shape; check before anything changes
            held = next(iter(self.entries.values())).buffer.observations()
            if obs["image"].shape[1:] != held["image"].shape[1:] or obs["proprio"].shape[1:] != held["proprio"].shape[1:]:
                raise ValueError(
                    f"obs frames {obs['image'].shape[1:]} / proprio {obs['proprio'].shape[1:]} differ from the "
                    f"bank's {held['image'].shape[1:]} / {held['proprio'].shape[1:]}"
                )
        episodes, groups = self._episodes(n, episode_indices, group_ids, strict)
        distances: dict[int, float] = {}
        p_values: dict[int, float | None] | None = None
        calibration: dict[str, Any] | None = None
        if self.mode == "ground_truth":
            if groups is None:
                raise ValueError("ground-truth mode needs group_ids for every assignment")
            group = batch_group(groups)
            if group in self.group_policy:
                pid, decision = self.group_policy[group], "recall"
            elif not self.entries:
                pid, decision = None, "adopt"
            elif len(self.entries) >= self.max_policies:
                pid, decision = self.current_policy_id, "recall_at_cap"
            else:
                pid, decision = None, "new"
        elif self.rule == "calibrated":
            cal = self.calibrated_distances(obs, self.calibration_rng if rng is None else rng, policies)
            distances, p_values = cal.distances, cal.p_values
            calibration = cal.record_info(self.false_split_rate, self.calibration_samples)
            pid, decision = decide_calibrated(distances, cal.accepted, self.max_policies, len(self.entries))
            if decision == "recall":
                pid = self._prefer_trained(pid, distances, cal.accepted)
        else:
            distances = self.distances(obs, policies)
            pid, decision = decide(distances, self.threshold, self.max_policies, len(self.entries))
            if decision == "recall":
                pid = self._prefer_trained(pid, distances, {p: d <= self.threshold for p, d in distances.items()})
        if pid is None:
            pid = self.next_policy_id()
        record = AssignmentRecord(
            index=len(self.history),
            policy_id=int(pid),
            decision=decision,
            new=decision in ("adopt", "new"),
            distances=distances,
            threshold=self.threshold,
            metric=self.metric,
            mode=self.mode,
            num_observations=n,
            episode_indices=episodes,
            wall_time_ms=0.0,
            time_unix=time.time(),
            true_groups=groups,
            p_values=p_values,
            calibration=calibration,
        )
        return record, t0

    def what_if(
        self,
        obs: dict[str, np.ndarray],
        *,
        episode_indices: Sequence[int] | None = None,
        group_ids: int | Sequence[int] | None = None,
        policies: Sequence[int] | None = None,
    ) -> AssignmentRecord:
        """The record :meth:`assign` would return for ``obs``, without changing any state.

        Unlike :meth:`assign`, any number of frames is accepted (a query, not episodes).
        ``policies`` restricts the comparison to those policy ids (the bank's size still decides
        ``recall_at_cap``, and a ``new`` policy still gets the id after the bank's largest).
        """
        rng = calibration_generator(self.seed)
        rng.bit_generator.state = self.calibration_rng.bit_generator.state  # a copy: no state changes
        record, t0 = self._plan(obs, episode_indices, group_ids, strict=False, rng=rng, policies=policies)
        record.wall_time_ms = (time.perf_counter() - t0) * 1e3
        return record

    def assign(
        self,
        obs: dict[str, np.ndarray],
        *,
        episode_indices: Sequence[int] | None = None,
        group_ids: int | Sequence[int] | None = None,
    ) -> AssignmentRecord:
        """Assign the episodes behind ``obs`` (their first-k frames) to a policy; see the module doc.

        The chosen policy becomes :attr:`current_policy_id` and its buffer takes ``obs``. Every
        ``merge_every`` assignments (with ``merge_threshold`` set) the bank first heals
        (:meth:`heal`); the merges it made are in the record's ``merges``.
        """
        merges = self.heal() if self._heal_due() else []
        record, t0 = self._plan(obs, episode_indices, group_ids)
        record.merges = merges or None
        pid = record.policy_id
        if record.new:
            seq = np.random.SeedSequence([self.seed, pid])
            self.entries[pid] = PolicyEntry(
                policy_id=pid,
                buffer=ObservationBuffer(self.buffer_size, self.replacement, seed=seq),
                created_at_episode=record.episode_indices[0],
                created_at_assignment=record.index,
                created_at_time=record.time_unix,
            )
        entry = self.entries[pid]
        if self.mode == "ground_truth" and record.true_groups is not None and record.decision != "recall_at_cap":
            self.group_policy[batch_group(record.true_groups)] = pid
        entry.buffer.add(obs)
        entry.episodes.extend(record.episode_indices)
        self.episode_policy.update((e, pid) for e in record.episode_indices)
        entry.assignments += 1
        if record.true_groups is not None:
            entry.group_counts.update(record.true_groups)
            for e, g in zip(record.episode_indices, record.true_groups):
                self._label(e, pid, g)
        self.next_episode = max(self.next_episode, max(record.episode_indices) + 1)
        self.current_policy_id = pid
        record.wall_time_ms = (time.perf_counter() - t0) * 1e3
        self.history.append(record)
        return record

    # ---- healing ----------------------------------------------------------------------------------
    def next_policy_id(self) -> int:
        """The id a new policy gets: one past every id the bank has used (retired ones included)."""
        used = list(self.entries) + list(self.retired)
        return max(used) + 1 if used else 0

    def _prefer_trained(self, nearest: int, distances: dict[int, float], accepted: dict[int, bool]) -> int:
        """Among the policies that accept and lie within ``tie_margin`` of ``nearest``'s distance
        (``d <= d_nearest / (1 - tie_margin)``), the one that has been assigned most often (ties:
        the nearer, then the lower id)."""
        if not self.tie_margin:
            return nearest
        reach = distances[nearest] / (1.0 - self.tie_margin)
        near = [p for p, d in distances.items() if accepted.get(p) and d <= reach and p in self.entries]
        return max(near, key=lambda p: (self.entries[p].assignments, -distances[p], -p), default=nearest)

    def _heal_due(self) -> bool:
        return (
            self.merge_threshold is not None
            and self.mode == "distance"
            and len(self.entries) >= 2
            and len(self.history) % self.merge_every == 0
        )

    def heal(self) -> list[dict[str, Any]]:
        """Merge every policy whose buffer is indistinguishable from an older policy's.

        Youngest first, policy ``j`` with at least :data:`MIN_MERGE_FRAMES` buffered frames is
        compared, as a batch, with the buffer of every older (lower-id) policy ``i``: ``d(B_j, B_i)``
        with the bank's metric, features and normalization (``B_i``'s spread). The nearest ``i``
        with ``d <= merge_threshold`` absorbs ``j`` (:meth:`merge`); the scan starts again until
        no pair merges. Returns the merge records (also appended to :attr:`merges`)."""
        out: list[dict[str, Any]] = []
        if self.merge_threshold is None or self.mode != "distance":
            return out
        merged = True
        while merged and len(self.entries) >= 2:
            merged = False
            for j in sorted(self.entries, reverse=True):
                older = [i for i in self.policy_ids if i < j]
                if not older or len(self.entries[j].buffer) < MIN_MERGE_FRAMES:
                    continue
                d = self.distances(self.entries[j].buffer.observations(), policies=older)
                i = min(sorted(d), key=lambda p: d[p])
                if d[i] <= self.merge_threshold:
                    out.append(self.merge(j, i, distance=d[i]))
                    merged = True
                    break
        return out

    def merge(self, retired: int, into: int, distance: float | None = None) -> dict[str, Any]:
        """Retire policy ``retired`` into ``into``: its buffered frames join ``B_into`` (by the
        buffer's replacement rule), its episodes and labels become ``into``'s, and it is never
        compared or chosen again (kept in :attr:`retired`; its id is never reused). Its learner's
        weights are not blended: ``into`` keeps its own, and the caller stops training ``retired``."""
        if retired == into or retired not in self.entries or into not in self.entries:
            raise ValueError(f"cannot merge policy {retired!r} into {into!r}; the bank holds {self.policy_ids}")
        gone, keep = self.entries.pop(retired), self.entries[into]
        if len(gone.buffer):
            keep.buffer.add(gone.buffer.observations())
        keep.episodes = sorted(keep.episodes + gone.episodes)
        keep.group_counts.update(gone.group_counts)
        self.episode_policy.update((e, into) for e in gone.episodes)
        self.labels = {e: ((into if p == retired else p), g) for e, (p, g) in self.labels.items()}
        self.rebuild_label_table()
        self.group_policy = {g: (into if p == retired else p) for g, p in self.group_policy.items()}
        if self.current_policy_id == retired:
            self.current_policy_id = into
        self.retired[retired] = gone
        record = {
            "retired": int(retired),
            "into": int(into),
            "distance": None if distance is None else float(distance),
            "at_assignment": len(self.history),
            "episodes": len(gone.episodes),
            "assignments": gone.assignments,
            "time_unix": time.time(),
        }
        self.merges.append(record)
        return record

    def record_episode_stats(
        self,
        policy_id: int,
        success: float | None = None,
        ret: float | None = None,
        group_id: int | None = None,
        episode_index: int | None = None,
    ) -> None:
        """Report one finished episode of ``policy_id`` (latest success and return per policy).

        With both ``group_id`` and ``episode_index``, an episode not yet labelled (one run between
        assignment steps) joins the metrics as a (policy, group) pair.
        """
        if policy_id not in self.entries:
            raise ValueError(f"unknown policy_id {policy_id!r}; the bank holds {self.policy_ids}")
        entry = self.entries[policy_id]
        for name, v in (("success", success), ("ret", ret)):
            if v is not None and (not isinstance(v, (int, float, np.number)) or not math.isfinite(float(v))):
                raise ValueError(f"{name} must be a finite number or None, got {v!r}")
        entry.episodes_reported += 1
        entry.last_success = None if success is None else float(success)
        entry.last_return = None if ret is None else float(ret)
        if group_id is not None and episode_index is not None:
            e = check_int("episode_index", episode_index, 0)
            if e not in self.labels:
                g = check_int("group_id", group_id, 0)
                self._label(e, int(policy_id), g)
                entry.group_counts[g] += 1
                self.next_episode = max(self.next_episode, e + 1)

    # ---- metrics ----------------------------------------------------------------------------------
    def _label(self, episode: int, policy_id: int, group_id: int) -> None:
        old = self.labels.get(episode)
        if old is not None:
            self.label_table[old] -= 1
        self.labels[episode] = (policy_id, group_id)
        self.label_table[(policy_id, group_id)] += 1

    def rebuild_label_table(self) -> None:
        """Recount :attr:`label_table` from :attr:`labels` (after loading or relabelling them)."""
        self.label_table = Counter(self.labels.values())

    def label_pairs(self) -> tuple[list[int], list[int]]:
        """(policy ids, true group ids) of every labelled episode, in episode order."""
        keys = sorted(self.labels)
        return [self.labels[e][0] for e in keys], [self.labels[e][1] for e in keys]

    def metrics(self) -> dict[str, Any]:
        """ARI over every labelled episode so far, per-policy counts, and the confusion table, from
        the label table (their cost grows with policies and groups, not with episodes)."""
        return table_metrics(self.label_table)

    def summary(self) -> dict[str, Any]:
        """JSON-safe overview: settings, current policy, every entry, and the metrics."""
        return {
            "metric": self.metric,
            "threshold": self.threshold,
            "mode": self.mode,
            "feature_norm": self.feature_norm,
            "buffer_size": self.buffer_size,
            "replacement": self.replacement,
            "max_policies": self.max_policies,
            **(
                {"rule": self.rule, "false_split_rate": self.false_split_rate,
                 "calibration_samples": self.calibration_samples}
                if self.rule == "calibrated" else {}
            ),
            **(
                {"merge_threshold": self.merge_threshold, "merge_every": self.merge_every}
                if self.merge_threshold is not None else {}
            ),
            "tie_margin": self.tie_margin,
            "num_policies": len(self.entries),
            "policies_created": len(self.entries) + len(self.retired),
            "retired": [
                {**self.retired[p].summary(), "merged_into": m["into"]}
                for m in self.merges for p in [m["retired"]] if p in self.retired
            ],
            "merges": [dict(m) for m in self.merges],
            "current_policy_id": self.current_policy_id,
            "assignments": len(self.history),
            "policies": [self.entries[p].summary() for p in self.policy_ids],
            "metrics": self.metrics(),
        }
