"""Actor-critic networks: the escnn equivariant policy and its plain-CNN twin.

:func:`build_actor_critic` is the one factory; both kinds share the :class:`ActorCritic`
interface (forward, features, evaluate_actions, act, features_np, get_weights / set_weights).
See docs/guide/models.md for the design and docs/research/models.md for the equivariance checks and the measured throughput.
"""

from __future__ import annotations

import math

import torch

from ..config import NetworkConfig
from ..envs.layout import ObsLayout
from ..symmetry import get_group
from .actor_critic import ActorCritic, gaussian_entropy, gaussian_log_prob
from .checks import equivariance_errors

__all__ = [
    "ActorCritic",
    "build_actor_critic",
    "cnn_width",
    "equivariance_errors",
    "gaussian_log_prob",
    "gaussian_entropy",
    "KINDS",
]

KINDS: tuple[str, ...] = ("equivariant", "cnn")


def cnn_width(net_cfg: NetworkConfig) -> float:
    """Channel multiplier of the CNN twin: ``net_cfg.cnn_width`` or sqrt(|network.group|)."""
    if net_cfg.cnn_width is not None:
        return float(net_cfg.cnn_width)
    return math.sqrt(get_group(net_cfg.group).order)


def build_actor_critic(
    net_cfg: NetworkConfig, layout: ObsLayout, kind: str | None = None, seed: int | None = None
) -> ActorCritic:
    """Build the actor-critic described by ``net_cfg`` for observations laid out as ``layout``.

    ``kind`` (``"equivariant"`` or ``"cnn"``) overrides ``net_cfg.kind``. With ``seed`` the
    initial weights are drawn from that seed without touching the global torch RNG; without it
    they come from the global RNG.
    """
    if not isinstance(net_cfg, NetworkConfig):
        raise TypeError(f"net_cfg must be a NetworkConfig, got {type(net_cfg).__name__}")
    if not isinstance(layout, ObsLayout):
        raise TypeError(f"layout must be an ObsLayout, got {type(layout).__name__}")
    kind = net_cfg.kind if kind is None else kind
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {list(KINDS)}, got {kind!r}")
    if seed is None:
        return _build(net_cfg, layout, kind)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return _build(net_cfg, layout, kind)


def _build(net_cfg: NetworkConfig, layout: ObsLayout, kind: str) -> ActorCritic:
    core = _core(net_cfg, layout, kind)
    if net_cfg.critic == "separate":  # drawn after the actor core: the actor's weights match a shared build's
        from .critic import SeparateCritic

        core = SeparateCritic(core, _core(net_cfg, layout, kind))
    return ActorCritic(
        core, layout, net_cfg.init_log_std, kind, proprio_norm=net_cfg.proprio_norm, action_mean=net_cfg.action_mean
    )


def _core(net_cfg: NetworkConfig, layout: ObsLayout, kind: str) -> torch.nn.Module:
    if kind == "equivariant":
        from .equivariant import EquivariantCore

        return EquivariantCore(layout, net_cfg.group, list(net_cfg.channels), net_cfg.hidden, net_cfg.space_to_depth)
    from .cnn import CNNCore

    return CNNCore(layout, list(net_cfg.channels), net_cfg.hidden, cnn_width(net_cfg), net_cfg.space_to_depth)
