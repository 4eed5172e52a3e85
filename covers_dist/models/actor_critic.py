"""The actor-critic interface shared by the equivariant network and its CNN twin.

An :class:`ActorCritic` wraps a *core* (the feature extractor and heads) with everything that is
the same for both kinds: input checks and conversion, the diagonal Gaussian policy, batched
no-grad inference for rollout workers, and weight transport.

Cores are ``nn.Module`` s with ``forward(image, proprio) -> (mean, value, features)`` on float
tensors (image ``(B, 3, S, S)`` in [0, 1], proprio ``(B, P)``), a ``feature_dim`` attribute and
``export_fast()``, which returns a plain-torch copy for inference (same outputs, no autograd).

The Gaussian's mean is ``tanh`` of the core's mean output (``action_mean="tanh"``), so it stays in
the action box [-1, 1] that the environments clip to; ``"linear"`` uses the output as it is. tanh
acts per entry and is odd, so it commutes with the signed permutations by which D4 and its
subgroups act on a planar pair: an equivariant core stays exactly equivariant.

The standard deviation is state independent and invariant: one log-std per planar action pair
(shared by its x and y entries) and one per invariant action entry, so a rotation or mirror of the
mean leaves the Gaussian's shape unchanged.

**Weights** (:meth:`ActorCritic.get_weights`) are the learnable parameters only, named as in
``state_dict()``, as CPU tensors. They do not depend on train/eval mode (escnn's cached filters
and sampled bases are derived data and are rebuilt from the parameters), so weights taken in one
mode load in the other, and ``set_weights(get_weights())`` round-trips exactly.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np
import torch
from torch import nn

from ..envs.layout import ObsLayout

__all__ = ["ACTION_MEANS", "ActorCritic", "gaussian_log_prob", "gaussian_entropy", "FEATURE_CHUNK"]

#: How the core's mean output becomes the Gaussian's mean (module docs).
ACTION_MEANS = ("tanh", "linear")
#: Observations per chunk in :meth:`ActorCritic.features_np` (bounds peak memory).
FEATURE_CHUNK = 256
_LOG_2PI = math.log(2.0 * math.pi)
#: Seed of the probe weights and input of :meth:`ActorCritic.probe_outputs`.
PROBE_SEED = 20240611


def gaussian_log_prob(actions: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """Log-density of a diagonal Gaussian, summed over the last dimension."""
    z = (actions - mean) * torch.exp(-log_std)
    return (-0.5 * z.pow(2) - log_std - 0.5 * _LOG_2PI).sum(-1)


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    """Entropy of a diagonal Gaussian, summed over the last dimension."""
    return (0.5 + 0.5 * _LOG_2PI + log_std).sum(-1)


class ActorCritic(nn.Module):
    """A Gaussian actor-critic over ``layout``'s observations and actions (see module docs)."""

    def __init__(
        self,
        core: nn.Module,
        layout: ObsLayout,
        init_log_std: float,
        kind: str,
        proprio_norm: bool = False,
        action_mean: str = "tanh",
    ) -> None:
        super().__init__()
        self.core = core
        self.layout = layout
        self.kind = kind
        if action_mean not in ACTION_MEANS:
            raise ValueError(f"action_mean must be one of {list(ACTION_MEANS)}, got {action_mean!r}")
        self.action_mean = action_mean
        if proprio_norm and not layout.has_proprio_stats:
            raise ValueError("network.proprio_norm needs a layout with proprio statistics; this task family has none")
        self.proprio_norm = bool(proprio_norm)
        if self.proprio_norm:  # fixed statistics, not weights (persistent=False: weights stay the parameters)
            self.register_buffer("proprio_shift", torch.tensor(layout.proprio_shift, dtype=torch.float32), persistent=False)
            self.register_buffer("proprio_scale", torch.tensor(layout.proprio_scale, dtype=torch.float32), persistent=False)
        self.feature_dim: int = int(core.feature_dim)
        pairs, scalars = layout.action_pairs, layout.action_scalars
        self.log_std_free = nn.Parameter(torch.full((pairs + scalars,), float(init_log_std)))
        index = [i for i in range(pairs) for _ in range(2)] + [pairs + j for j in range(scalars)]
        self.register_buffer("std_index", torch.tensor(index, dtype=torch.long), persistent=False)
        # plain dict, so the exported copy is not registered as a submodule (not in the weights)
        self._fast_cache: dict[str, Any] = {}

    # ---- inputs ------------------------------------------------------------------------------
    def prepare(self, obs: Mapping[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """Check a batched observation dict and convert it to (image (B,3,S,S) float, proprio)."""
        if not isinstance(obs, Mapping) or "image" not in obs or "proprio" not in obs:
            raise TypeError(f"obs must be a mapping with 'image' and 'proprio', got {type(obs).__name__}")
        image, proprio = obs["image"], obs["proprio"]
        if not isinstance(image, torch.Tensor) or not isinstance(proprio, torch.Tensor):
            raise TypeError("obs['image'] and obs['proprio'] must be torch tensors (use act/features_np for numpy)")
        s, p = self.layout.image_size, self.layout.proprio_dim
        if image.dtype != torch.uint8:
            raise TypeError(f"obs['image'] must be uint8 (B, {s}, {s}, 3), got dtype {image.dtype}")
        if image.dim() != 4 or tuple(image.shape[1:]) != (s, s, 3):
            raise ValueError(f"obs['image'] must have shape (B, {s}, {s}, 3), got {tuple(image.shape)}")
        if proprio.dim() != 2 or proprio.shape[1] != p or proprio.shape[0] != image.shape[0]:
            raise ValueError(f"obs['proprio'] must have shape ({image.shape[0]}, {p}), got {tuple(proprio.shape)}")
        device = self.log_std_free.device
        img = image.to(device).permute(0, 3, 1, 2).to(torch.float32).div_(255.0)
        proprio = proprio.to(device=device, dtype=torch.float32)
        if self.proprio_norm:
            proprio = (proprio - self.proprio_shift) * self.proprio_scale
        return img, proprio

    def _numpy_obs(self, obs_np: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        if not isinstance(obs_np, Mapping) or "image" not in obs_np or "proprio" not in obs_np:
            raise TypeError(f"obs must be a mapping with 'image' and 'proprio', got {type(obs_np).__name__}")
        image = np.asarray(obs_np["image"])
        if image.dtype != np.uint8:
            raise TypeError(f"obs['image'] must be uint8, got {image.dtype}")
        proprio = np.asarray(obs_np["proprio"], dtype=np.float32)
        image, proprio = np.ascontiguousarray(image), np.ascontiguousarray(proprio)
        if not image.flags.writeable:  # torch.from_numpy warns on read-only arrays
            image = image.copy()
        if not proprio.flags.writeable:
            proprio = proprio.copy()
        return {"image": torch.from_numpy(image), "proprio": torch.from_numpy(proprio)}

    # ---- policy ------------------------------------------------------------------------------
    def policy_mean(self, raw: torch.Tensor) -> torch.Tensor:
        """The Gaussian's mean from the core's mean output (``tanh`` or as is; module docs)."""
        return torch.tanh(raw) if self.action_mean == "tanh" else raw

    def log_std(self) -> torch.Tensor:
        """Per-dimension log standard deviation (A,), tied within each planar pair."""
        return self.log_std_free[self.std_index]

    def forward(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(mean (B, A), log_std (B, A), value (B,))`` for a batch of observations."""
        img, proprio = self.prepare(obs)
        mean, value, _ = self.core(img, proprio)
        # fp32 out of a bf16 autocast forward: the Gaussian's log-probs (PPO's ratio) need fp32
        mean, value = self.policy_mean(mean.float()), value.float()
        return mean, self.log_std().expand_as(mean), value

    def features(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Invariant (equivariant net) or pooled (CNN twin) features, shape (B, feature_dim)."""
        img, proprio = self.prepare(obs)
        return self.core(img, proprio)[2]

    def evaluate_actions(
        self, obs: Mapping[str, torch.Tensor], actions: torch.Tensor, return_mean: bool = False
    ) -> tuple[torch.Tensor, ...]:
        """``(log_prob (B,), entropy (B,), value (B,))`` of ``actions`` under the current policy
        (``return_mean``: and the Gaussian's mean (B, A) last)."""
        mean, log_std, value = self(obs)
        if actions.shape != mean.shape:
            raise ValueError(f"actions must have shape {tuple(mean.shape)}, got {tuple(actions.shape)}")
        logp = gaussian_log_prob(actions.to(device=mean.device, dtype=mean.dtype), mean, log_std)
        if return_mean:
            return logp, gaussian_entropy(log_std), value, mean
        return logp, gaussian_entropy(log_std), value

    # ---- fast inference ----------------------------------------------------------------------
    def fast_core(self) -> nn.Module:
        """The exported inference core (channels-last), rebuilt whenever a parameter changed in place.

        Parameter changes are detected through their in-place version counters (optimizer steps,
        ``set_weights`` and ``load_state_dict`` all bump them).
        """
        cache = self._fast_cache
        if "params" not in cache:  # walking escnn's module tree costs milliseconds; do it once
            cache["params"] = list(self.parameters())
        device = self.log_std_free.device
        key = (device, *(p._version for p in cache["params"]))
        if cache.get("key") != key:
            # escnn's export builds modules (random initial weights, then overwritten): keep the
            # caller's random stream as it was, so when an export happens never changes a result
            with torch.random.fork_rng(devices=[]):
                cache["core"] = self.core.export_fast().to(device=device, memory_format=torch.channels_last)
            cache["key"] = key
        return cache["core"]

    def invalidate_fast(self) -> None:
        """Forget the exported inference core (done automatically on any in-place change)."""
        self._fast_cache.clear()

    @torch.no_grad()
    def act(
        self,
        obs_np: Mapping[str, Any],
        deterministic: bool = False,
        generator: torch.Generator | None = None,
        noise: torch.Tensor | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample actions for a batch of numpy observations (rollout workers).

        Returns ``(actions float32 (B, A), log_probs float32 (B,), values float32 (B,))``; with
        ``deterministic`` the actions are the means (log-probs are still those of the Gaussian).
        Runs the exported core under ``torch.no_grad``; ``generator`` makes sampling reproducible;
        ``noise`` (B, A), standard normal, replaces the noise drawn here (coloured noise,
        :mod:`covers_dist.ppo.noise`).
        """
        img, proprio = self.prepare(self._numpy_obs(obs_np))
        mean, value, _ = self.fast_core()(img.contiguous(memory_format=torch.channels_last), proprio)
        mean = self.policy_mean(mean)
        log_std = self.log_std().expand_as(mean)
        if deterministic:
            actions = mean
        else:
            if noise is None:
                noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
            elif tuple(noise.shape) != tuple(mean.shape):
                raise ValueError(f"noise must have shape {tuple(mean.shape)}, got {tuple(noise.shape)}")
            actions = mean + noise.to(mean.device) * log_std.exp()
        logp = gaussian_log_prob(actions, mean, log_std)
        return (
            actions.cpu().numpy().astype(np.float32),
            logp.cpu().numpy().astype(np.float32),
            value.cpu().numpy().astype(np.float32),
        )

    @torch.no_grad()
    def features_np(self, obs_np: Mapping[str, Any], chunk: int = FEATURE_CHUNK) -> np.ndarray:
        """Features (B, feature_dim) as float32 for numpy observations, computed in chunks."""
        obs = self._numpy_obs(obs_np)
        n = obs["image"].shape[0]
        fast = self.fast_core()
        out = np.empty((n, self.feature_dim), dtype=np.float32)
        for start in range(0, n, chunk):
            part = {k: v[start : start + chunk] for k, v in obs.items()}
            img, proprio = self.prepare(part)
            feats = fast(img.contiguous(memory_format=torch.channels_last), proprio)[2]
            out[start : start + chunk] = feats.cpu().numpy()
        return out

    # ---- weights -----------------------------------------------------------------------------
    def get_weights(self) -> dict[str, torch.Tensor]:
        """The learnable parameters as detached CPU copies (mode independent; see module docs)."""
        return {name: p.detach().to("cpu", copy=True) for name, p in self.named_parameters()}

    def set_weights(self, weights: Mapping[str, torch.Tensor]) -> None:
        """Load weights from :meth:`get_weights`; names and shapes must match exactly."""
        params = dict(self.named_parameters())
        missing, unknown = sorted(set(params) - set(weights)), sorted(set(weights) - set(params))
        if missing or unknown:
            raise ValueError(f"weights do not match the model: missing {missing[:5]}, unexpected {unknown[:5]}")
        for name, p in params.items():
            w = weights[name]
            if not isinstance(w, torch.Tensor) or tuple(w.shape) != tuple(p.shape):
                shape = tuple(w.shape) if isinstance(w, torch.Tensor) else type(w).__name__
                raise ValueError(f"weights[{name!r}] must be a tensor of shape {tuple(p.shape)}, got {shape}")
        with torch.no_grad():
            for name, p in params.items():
                p.copy_(weights[name])
        if not self.training:  # refresh escnn's eval-mode filter caches
            self.train(True)
            self.train(False)
        self.invalidate_fast()

    def probe_outputs(self, batch: int = 4) -> np.ndarray:
        """The core's outputs (mean, value, features) for fixed probe weights on a fixed probe input.

        Two processes that build the same network compute the same function of the same weights
        only if every constant derived at build time (escnn's bases and changes of basis) is the
        same; this is the check: equal arrays (up to float rounding) in every process. The probe
        weights and input come from a fixed ``torch.Generator``; the model's own weights, mode and
        the global random state are left as they were.
        """
        gen = torch.Generator().manual_seed(PROBE_SEED)
        saved, was_training = self.get_weights(), self.training
        probe = {n: 0.1 * torch.randn(w.shape, generator=gen) for n, w in sorted(saved.items())}
        s, p = self.layout.image_size, self.layout.proprio_dim
        image = torch.rand(batch, 3, s, s, generator=gen)
        proprio = torch.randn(batch, p, generator=gen)
        device = self.log_std_free.device
        try:
            self.set_weights(probe)
            self.eval()
            with torch.no_grad():
                mean, value, features = self.core(image.to(device), proprio.to(device))
            parts = [mean.float().flatten(), value.float().flatten(), features.float().flatten()]
            return torch.cat(parts).cpu().numpy().astype(np.float64)
        finally:
            self.set_weights(saved)
            self.train(was_training)

    def num_parameters(self) -> int:
        """Number of learnable scalars."""
        return sum(p.numel() for p in self.parameters())
