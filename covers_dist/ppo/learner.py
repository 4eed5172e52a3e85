"""The PPO learner: episodes in, one PPO update of an actor-critic out (pure torch, no Ray).

:meth:`PPOLearner.update` takes episodes in the format of docs/guide/architecture.md, computes GAE per
episode (:func:`covers_dist.ppo.gae.compute_gae`, on rewards times ``reward_scale``, divided with
``reward_norm: return`` by the running standard deviation of the discounted return), then runs
``epochs`` passes of shuffled minibatches of the clipped objective
(:func:`covers_dist.ppo.loss.ppo_loss`) with the behaviour log-probs and values stored in the data,
gradient-norm clipping and Adam. With ``precision`` bf16 (``auto``: where the learner's device
computes bf16 natively) the forward pass runs under ``torch.autocast``; weights, Adam's state, the
loss and the gradients' accumulation stay fp32. Minibatches split each epoch's shuffled samples into
``round(N / minibatch_size)`` near-equal parts, so every sample is used every epoch. A minibatch whose loss or
gradient norm is not finite is skipped (no optimizer step, the weights stay as they were) and
counted in ``skipped_steps``. With ``target_kl`` set, the update stops at the first minibatch
whose approximate KL to the behaviour policy (``kl_reference: update_start``: to the policy at the
start of this update) exceeds it (that minibatch is not applied).

The learning rate follows ``lr_schedule``: constant, or linear from ``lr`` at update 0 to 0 at
update ``total_updates`` (and 0 after; a run's learners get ``Config.learner_ppo``, where a null
``total_updates`` is the run's length in updates); the entropy bonus follows ``ent_schedule`` on
the same ramp (``ent_coef`` falling to 0 at ``total_updates``). With ``log_std_cap`` set, after
each update the model's learned log standard deviation is clipped to at most
:func:`log_std_cap_at` of the update count: a bound falling linearly from the value the model started with to ``log_std_cap`` at
``total_updates`` (the rollout workers get the clipped value with the weights, so every episode is
acted by the standard deviation its update was computed for). The learner owns the optimizer; :meth:`state_dict`
covers the model weights, the optimizer, the update counters and the shuffling RNG.

Episodes acted by another network (``update(..., reevaluate=...)``, the runtime's batch acted by
another policy than the one it was assigned to) first have their ``logprob`` and ``value``
recomputed by this learner's model (:meth:`PPOLearner.reevaluate`): GAE then uses this network's
values, on its own return scale, and the ratio's old log-prob is this network's, so the first
minibatch is on-policy. Other episodes are used as stored (docs/research/learning.md, "A batch acted by
another policy").
"""

from __future__ import annotations

import copy
import math
import time
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from ..config import PPOConfig
from .gae import compute_gae
from .loss import normalize_advantages, ppo_loss

__all__ = [
    "PPOLearner", "ReturnNormalizer", "episodes_to_batch", "log_std_cap_at", "resolve_precision", "native_bf16_cpu",
    "EPISODE_KEYS", "STAT_KEYS",
]  # fmt: skip

EPISODE_KEYS = ("image", "proprio", "action", "logprob", "value", "reward", "success", "terminated", "truncated")
#: Keys of the dict returned by :meth:`PPOLearner.update`.
STAT_KEYS = (
    "policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "explained_variance", "grad_norm",
    "skipped_steps", "optimizer_steps", "epochs_completed", "early_stopped", "lr", "num_samples",
    "num_episodes", "episode_return_mean", "success_rate", "update_time_s", "samples_per_s", "update_count", "bf16", "reward_divisor",
    "bound_loss", "mean_out_of_box", "reevaluated_samples", "log_std_cap",
)  # fmt: skip


def native_bf16_cpu(cpuinfo: str = "/proc/cpuinfo") -> bool:
    """Whether this CPU computes bf16 natively (AVX-512 BF16 or AMX); False when unknown."""
    try:
        with open(cpuinfo) as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return bool(flags & {"avx512_bf16", "amx_bf16"})
    except OSError:
        pass
    return False


def resolve_precision(setting: str, device: torch.device | str) -> str:
    """``"fp32"`` or ``"bf16"`` for ``ppo.precision`` on ``device`` (``auto``: bf16 where it is native)."""
    if setting not in ("auto", "fp32", "bf16"):
        raise ValueError(f"precision must be 'auto', 'fp32' or 'bf16', got {setting!r}")
    if setting != "auto":
        return setting
    device = torch.device(device)
    if device.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "fp32"
    return "bf16" if device.type == "cpu" and native_bf16_cpu() else "fp32"


def _check_episode(i: int, ep: Mapping[str, Any]) -> int:
    if not isinstance(ep, Mapping):
        raise TypeError(f"episode {i} must be a dict, got {type(ep).__name__}")
    missing = [k for k in EPISODE_KEYS if k not in ep]
    if missing:
        raise ValueError(f"episode {i} lacks keys {missing}")
    t = len(ep["action"])
    if t < 1:
        raise ValueError(f"episode {i} has no steps")
    expected = {"image": t + 1, "proprio": t + 1, "logprob": t, "value": t + 1, "reward": t, "success": t}
    for key, n in expected.items():
        if len(ep[key]) != n:
            raise ValueError(f"episode {i}: {key} has {len(ep[key])} entries, expected {n} (action has {t})")
    if np.asarray(ep["image"]).dtype != np.uint8:
        raise TypeError(f"episode {i}: image must be uint8, got {np.asarray(ep['image']).dtype}")
    return t


def episodes_to_batch(
    episodes: Sequence[Mapping[str, Any]],
    gamma: float,
    lam: float,
    reward_scale: float = 1.0,
    return_norm: "ReturnNormalizer | None" = None,
) -> dict[str, torch.Tensor]:
    """Flatten episodes into training tensors, with GAE advantages and returns per episode.

    Rewards are multiplied by ``reward_scale`` first (values and returns live on that scale). With
    ``return_norm``, the scaled rewards of these episodes are merged into its statistics once every
    episode has passed the checks (a rejected batch leaves them as they were), and the rewards are
    then divided by its standard deviation.
    """
    if not episodes:
        raise ValueError("update needs at least one episode")
    lengths = [_check_episode(i, ep) for i, ep in enumerate(episodes)]
    scale = reward_scale
    if return_norm is not None:
        return_norm.update([np.asarray(ep["reward"], np.float64) * reward_scale for ep in episodes])
        scale = reward_scale / return_norm.std
    keys = ("image", "proprio", "action", "logprob", "value", "adv", "ret")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    for ep, t in zip(episodes, lengths):
        rewards = np.asarray(ep["reward"], np.float64) * scale
        adv, ret = compute_gae(rewards, ep["value"], bool(ep["terminated"]), bool(ep["truncated"]), gamma, lam)
        parts["image"].append(np.asarray(ep["image"])[:t])
        parts["proprio"].append(np.asarray(ep["proprio"], np.float32)[:t])
        parts["action"].append(np.asarray(ep["action"], np.float32))
        parts["logprob"].append(np.asarray(ep["logprob"], np.float32))
        parts["value"].append(np.asarray(ep["value"], np.float32)[:t])
        parts["adv"].append(adv)
        parts["ret"].append(ret)
    return {k: torch.from_numpy(np.ascontiguousarray(np.concatenate(v))) for k, v in parts.items()}


class ReturnNormalizer:
    """Running standard deviation of the discounted return, the divisor of ``reward_norm: return``.

    Each episode's discounted return ``G_t = r_t + gamma * G_{t-1}`` (``G_{-1} = 0``) is computed
    along the episode, as the environment pays it; the mean and variance of every ``G_t`` seen so
    far are merged in (Chan et al.'s parallel update), and rewards are divided by
    ``sqrt(var + eps)``. Dividing by the spread of the return (not of single rewards) keeps the
    value targets near unit scale whatever the task's reward range, as the strong PPO
    implementations do (Engstrom et al. 2020, "Implementation matters in deep RL").
    """

    def __init__(self, gamma: float, eps: float = 1e-8) -> None:
        self.gamma = float(gamma)
        self.eps = float(eps)
        self.count = 0
        self.mean = 0.0
        self.var = 1.0

    def update(self, episodes_rewards: Sequence[np.ndarray]) -> None:
        """Merge the discounted returns of these episodes' steps into the running statistics."""
        returns = []
        for r in episodes_rewards:
            g, out = 0.0, np.empty(len(r), np.float64)
            for t, x in enumerate(np.asarray(r, np.float64)):
                g = x + self.gamma * g
                out[t] = g
            returns.append(out)
        x = np.concatenate(returns) if returns else np.empty(0)
        x = x[np.isfinite(x)]  # a NaN/inf reward spoils its own update (skipped steps), not the statistics
        if x.size == 0:
            return
        n, mean, var = x.size, float(x.mean()), float(x.var())
        if self.count == 0:
            self.count, self.mean, self.var = n, mean, var
            return
        total = self.count + n
        delta = mean - self.mean
        m2 = self.var * self.count + var * n + delta**2 * self.count * n / total
        self.count, self.mean, self.var = total, self.mean + delta * n / total, m2 / total

    @property
    def std(self) -> float:
        return math.sqrt(self.var + self.eps)

    def state_dict(self) -> dict[str, float]:
        return {"count": self.count, "mean": self.mean, "var": self.var}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.count, self.mean, self.var = int(state["count"]), float(state["mean"]), float(state["var"])


def _explained_variance(values: torch.Tensor, returns: torch.Tensor) -> float:
    var = float(returns.var(unbiased=False))
    return float("nan") if var == 0.0 else 1.0 - float((returns - values).var(unbiased=False)) / var


def scheduled_learning_rate(lr: float, schedule: str, update: int, total_updates: int | None) -> float:
    """The rate of update ``update`` (0-based): ``lr``, or for ``linear`` ``lr * max(0, 1 - update / total_updates)``."""
    if schedule == "constant":
        return lr
    return lr * max(0.0, 1.0 - update / int(total_updates or 1))


def log_std_cap_at(start: float, final: float, update: int, total_updates: int) -> float:
    """The cap on the log std after ``update`` updates: ``start`` at 0, linear to ``final`` at ``total_updates``, then held."""
    return start + (final - start) * min(1.0, update / max(1, int(total_updates)))


class PPOLearner:
    """PPO-clip updates of ``model`` (an :class:`covers_dist.models.ActorCritic`) as configured."""

    def __init__(self, model: torch.nn.Module, ppo_cfg: PPOConfig, seed: int = 0) -> None:
        if not isinstance(ppo_cfg, PPOConfig):
            raise TypeError(f"ppo_cfg must be a PPOConfig, got {type(ppo_cfg).__name__}")
        schedules = (
            ("ppo.lr_schedule=linear", ppo_cfg.lr_schedule == "linear"),
            ("ppo.ent_schedule=linear", ppo_cfg.ent_schedule == "linear"),
            ("ppo.log_std_cap", ppo_cfg.log_std_cap is not None),
        )
        for schedule, on in schedules:
            if on and ppo_cfg.total_updates is None:
                raise ValueError(
                    f"{schedule} needs ppo.total_updates; a null one is the run's length: "
                    "pass Config.learner_ppo, not Config.ppo"
                )
        for name in ("evaluate_actions", "get_weights", "set_weights"):
            if not callable(getattr(model, name, None)):
                raise TypeError(f"model must provide {name}() (an ActorCritic), got {type(model).__name__}")
        if ppo_cfg.log_std_cap is not None and not isinstance(getattr(model, "log_std_free", None), torch.Tensor):
            raise TypeError(f"ppo.log_std_cap needs a model with a learned log_std_free, got {type(model).__name__}")
        self.model = model
        self.cfg = ppo_cfg
        self.seed = int(seed)
        self.optimizer = torch.optim.Adam(model.parameters(), lr=ppo_cfg.lr, eps=1e-5)
        self.update_count = 0
        self.skipped_total = 0
        self._rng = torch.Generator().manual_seed(self.seed)
        device = next(model.parameters()).device
        self.precision = resolve_precision(ppo_cfg.precision, device)
        self._autocast_device = device.type
        self.return_norm = ReturnNormalizer(ppo_cfg.gamma) if ppo_cfg.reward_norm == "return" else None
        # where the falling cap starts: the model's log std before any update (network.init_log_std)
        self.log_std_start = float(model.log_std_free.detach().max()) if ppo_cfg.log_std_cap is not None else None
        # ppo.weight_average: the moving average of the weights (what `bench learn` evaluates), from the initial ones
        self.averaged = model.get_weights() if ppo_cfg.weight_average is not None else None

    def learning_rate(self) -> float:
        """The learning rate the next update will use."""
        return scheduled_learning_rate(self.cfg.lr, self.cfg.lr_schedule, self.update_count, self.cfg.total_updates)

    def entropy_coef(self) -> float:
        """The entropy-bonus coefficient the next update will use (``ent_schedule``, the same ramp as the rate)."""
        return scheduled_learning_rate(self.cfg.ent_coef, self.cfg.ent_schedule, self.update_count, self.cfg.total_updates)

    @torch.no_grad()
    def reevaluate(self, episodes: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
        """Copies of ``episodes`` whose ``logprob`` (T,) and ``value`` (T + 1,) are this model's.

        What a rollout worker holding these weights would have stored for the same observations and
        actions: fp32 (no autocast), eval mode, in chunks of ``minibatch_size`` observations. The
        episodes passed in are not modified (on Ray their arrays are read-only).
        """
        was_training = self.model.training
        self.model.eval()
        chunk = max(1, int(self.cfg.minibatch_size))
        out = []
        try:
            for i, ep in enumerate(episodes):
                t = _check_episode(i, ep)
                image = np.ascontiguousarray(np.asarray(ep["image"]))
                proprio = np.ascontiguousarray(np.asarray(ep["proprio"], np.float32))
                actions = np.asarray(ep["action"], np.float32).reshape(t, -1)
                # the last observation has no action; a zero action gives its value (its log-prob is dropped)
                actions = np.concatenate([actions, np.zeros((1, actions.shape[1]), np.float32)])
                logps, values = [], []
                for s in range(0, t + 1, chunk):
                    obs = {"image": torch.tensor(image[s : s + chunk]), "proprio": torch.tensor(proprio[s : s + chunk])}
                    logp, _, value = self.model.evaluate_actions(obs, torch.tensor(actions[s : s + chunk]))
                    logps.append(logp.float().cpu().numpy())
                    values.append(value.float().cpu().numpy())
                copied = dict(ep)
                copied["logprob"] = np.concatenate(logps)[:t].astype(np.float32)
                copied["value"] = np.concatenate(values).astype(np.float32)
                out.append(copied)
        finally:
            self.model.train(was_training)
        return out

    def update(self, episodes: Sequence[Mapping[str, Any]], reevaluate: Sequence[bool] | None = None) -> dict[str, Any]:
        """One PPO update on ``episodes``; returns the statistics listed in :data:`STAT_KEYS`.

        ``reevaluate`` (one flag per episode): episodes acted by another network, whose stored
        log-probs and values are replaced by this model's before GAE (:meth:`reevaluate`); their
        steps are counted in ``reevaluated_samples``.
        """
        cfg = self.cfg
        start = time.perf_counter()
        reevaluated = 0
        if reevaluate is not None:
            flags = [bool(f) for f in reevaluate]
            if len(flags) != len(episodes):
                raise ValueError(
                    f"reevaluate needs one flag per episode, got {len(flags)} for {len(episodes)} episodes"
                )
            if any(flags):
                for i, ep in enumerate(episodes):  # errors name the episode's place in the whole batch
                    _check_episode(i, ep)
                picked = [ep for ep, f in zip(episodes, flags) if f]
                fresh = iter(self.reevaluate(picked))
                episodes = [next(fresh) if f else ep for ep, f in zip(episodes, flags)]
                reevaluated = sum(len(ep["action"]) for ep in picked)
        batch = episodes_to_batch(episodes, cfg.gamma, cfg.gae_lambda, cfg.reward_scale, self.return_norm)
        scale = cfg.reward_scale if self.return_norm is None else cfg.reward_scale / self.return_norm.std
        n = batch["action"].shape[0]
        lr = self.learning_rate()
        ent_coef = self.entropy_coef()
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        params = [p for p in self.model.parameters() if p.requires_grad]
        device = params[0].device
        if device.type != "cpu":
            batch = {k: v.to(device) for k, v in batch.items()}
        was_training = self.model.training
        self.model.train()
        sums = {k: 0.0 for k in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "grad_norm", "bound_loss")}
        out_of_box = out_count = 0.0
        steps = skipped = epochs_done = processed = 0
        early = False
        num_mb = max(1, round(n / cfg.minibatch_size))
        start_logp = self._start_logprob(batch) if cfg.target_kl is not None and cfg.kl_reference == "update_start" else None
        for _ in range(cfg.epochs):
            for idx in torch.tensor_split(torch.randperm(n, generator=self._rng).to(device), num_mb):
                obs = {"image": batch["image"][idx], "proprio": batch["proprio"][idx]}
                with torch.autocast(self._autocast_device, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
                    logp, entropy, values, mean = self.model.evaluate_actions(obs, batch["action"][idx], return_mean=True)
                logp, entropy, values, mean = logp.float(), entropy.float(), values.float(), mean.float()
                if epochs_done == 0:  # how much of the mean lies outside the action box, over the first epoch
                    out_of_box += float((mean.detach().abs() > 1.0).float().sum())
                    out_count += mean.numel()
                adv = batch["adv"][idx]
                terms = ppo_loss(
                    logp, batch["logprob"][idx], normalize_advantages(adv) if cfg.norm_adv else adv,
                    values, batch["value"][idx], batch["ret"][idx], entropy,
                    cfg.clip_coef, cfg.vf_clip_coef, ent_coef, cfg.vf_coef,
                    mean=mean, bound_coef=cfg.bound_coef,
                )  # fmt: skip
                processed += len(idx)
                if cfg.target_kl is not None and self._moved(terms.approx_kl, logp, start_logp, idx) > cfg.target_kl:
                    early = True
                    break
                self.optimizer.zero_grad(set_to_none=True)
                if not torch.isfinite(terms.loss):
                    skipped += 1
                    continue
                terms.loss.backward()
                grad_norm = float(torch.nn.utils.clip_grad_norm_(params, cfg.max_grad_norm))
                if not math.isfinite(grad_norm):
                    self.optimizer.zero_grad(set_to_none=True)
                    skipped += 1
                    continue
                self.optimizer.step()
                steps += 1
                for key in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "bound_loss"):
                    sums[key] += getattr(terms, key)
                sums["grad_norm"] += grad_norm
            if early:
                break
            epochs_done += 1
        self.optimizer.zero_grad(set_to_none=True)
        self.model.train(was_training)
        self.update_count += 1
        cap = self._apply_log_std_cap()
        self._move_average()
        self.skipped_total += skipped
        elapsed = time.perf_counter() - start
        stats: dict[str, Any] = {k: (v / steps if steps else float("nan")) for k, v in sums.items()}
        stats.update(
            explained_variance=_explained_variance(batch["value"].cpu(), batch["ret"].cpu()),
            skipped_steps=skipped,
            optimizer_steps=steps,
            epochs_completed=epochs_done,
            early_stopped=early,
            lr=lr,
            num_samples=n,
            num_episodes=len(episodes),
            episode_return_mean=float(np.mean([np.sum(ep["reward"]) for ep in episodes])),
            success_rate=float(np.mean([float(np.max(ep["success"])) > 0 for ep in episodes])),
            update_time_s=elapsed,
            samples_per_s=processed / elapsed if elapsed > 0 else float("nan"),
            update_count=self.update_count,
            bf16=self.precision == "bf16",
            reward_divisor=1.0 / scale,  # raw rewards are divided by this before GAE
            mean_out_of_box=out_of_box / out_count if out_count else float("nan"),
            reevaluated_samples=reevaluated,
            log_std_cap=cap,  # None when off (not NaN: statistics compare equal across a retried update)
        )
        return stats

    @torch.no_grad()
    def _start_logprob(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Log-probs of the batch's actions under the model as it is before this update's first step,
        computed as the minibatches compute them (train mode, the update's precision)."""
        chunk = max(1, int(self.cfg.minibatch_size))
        out = []
        for s in range(0, batch["action"].shape[0], chunk):
            obs = {"image": batch["image"][s : s + chunk], "proprio": batch["proprio"][s : s + chunk]}
            with torch.autocast(self._autocast_device, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
                logp, _, _ = self.model.evaluate_actions(obs, batch["action"][s : s + chunk])
            out.append(logp.float())
        return torch.cat(out)

    @staticmethod
    def _moved(approx_kl: float, logp: torch.Tensor, start_logp: torch.Tensor | None, idx: torch.Tensor) -> float:
        """The approximate KL the stop reads: to the behaviour policy (``approx_kl``), or with
        ``kl_reference: update_start`` to the policy at the start of the update."""
        if start_logp is None:
            return approx_kl
        log_ratio = logp.detach() - start_logp[idx]
        return float(((log_ratio.exp() - 1.0) - log_ratio).mean())

    @torch.no_grad()
    def _apply_log_std_cap(self) -> float | None:
        """Clip the model's log std to the cap of the current update count; the cap, or None when off."""
        if self.log_std_start is None:  # set exactly when ppo.log_std_cap is
            return None
        cap = log_std_cap_at(self.log_std_start, self.cfg.log_std_cap, self.update_count, int(self.cfg.total_updates or 1))
        self.model.log_std_free.clamp_(max=cap)
        return cap

    @torch.no_grad()
    def _move_average(self) -> None:
        """One step of ``ppo.weight_average``'s moving average towards the weights after this update."""
        if self.averaged is None:
            return
        decay = float(self.cfg.weight_average)
        for name, w in self.model.get_weights().items():
            self.averaged[name].mul_(decay).add_(w, alpha=1.0 - decay)

    def averaged_weights(self) -> dict[str, torch.Tensor]:
        """A copy of the moving average of the weights (``ppo.weight_average``), in :meth:`get_weights`'s form."""
        if self.averaged is None:
            raise ValueError("no weight average is kept: set ppo.weight_average (a decay in (0, 1))")
        return {name: w.clone() for name, w in self.averaged.items()}

    # ---- checkpoints ---------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Model weights, optimizer state, counters and the shuffling RNG (deep copies)."""
        return {
            "model": self.model.get_weights(),
            "optimizer": copy.deepcopy(self.optimizer.state_dict()),
            "update_count": self.update_count,
            "skipped_total": self.skipped_total,
            "rng_state": self._rng.get_state(),
            "seed": self.seed,
            "return_norm": None if self.return_norm is None else self.return_norm.state_dict(),
            "log_std_start": self.log_std_start,
            "averaged": None if self.averaged is None else self.averaged_weights(),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore from :meth:`state_dict` (the model must have the same architecture)."""
        missing = [k for k in ("model", "optimizer", "update_count", "skipped_total", "rng_state") if k not in state]
        if missing:
            raise ValueError(f"learner state lacks keys {missing}")
        self.model.set_weights(state["model"])
        self.optimizer.load_state_dict(copy.deepcopy(state["optimizer"]))
        self.update_count = int(state["update_count"])
        self.skipped_total = int(state["skipped_total"])
        self._rng.set_state(state["rng_state"])
        self.seed = int(state.get("seed", self.seed))
        if self.cfg.log_std_cap is not None and state.get("log_std_start") is not None:
            self.log_std_start = float(state["log_std_start"])
        if self.averaged is not None:  # a state saved without an average starts it from its weights
            saved_avg = state.get("averaged")
            self.averaged = {n: w.clone() for n, w in (saved_avg or state["model"]).items()}
        saved = state.get("return_norm")
        if self.return_norm is not None:
            if saved is None:  # a learner saved without return normalisation: its statistics start afresh
                self.return_norm = ReturnNormalizer(self.cfg.gamma)
            else:
                self.return_norm.load_state_dict(saved)
