"""A core whose value comes from its own network (``network.critic: separate``).

The shared core (:class:`~covers_dist.models.equivariant.EquivariantCore` or its CNN twin) feeds
the policy head and the value head from one trunk, so the value loss moves the features the
policy reads. :class:`SeparateCritic` pairs two cores of the same shape: the mean and the
features (what the clustering compares) come from the actor core, the value from the critic
core, and neither loss reaches the other's weights. Each core keeps its own symmetry (the
equivariant critic's value is invariant by construction), so the pair is as exactly equivariant
as one core; it costs about twice the network's compute.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

__all__ = ["SeparateCritic"]


class SeparateCritic(nn.Module):
    """``forward(image, proprio) -> (actor's mean, critic's value, actor's features)``."""

    def __init__(self, actor: nn.Module, critic: nn.Module) -> None:
        super().__init__()
        self.actor = actor
        self.critic = critic
        self.feature_dim: int | None = getattr(actor, "feature_dim", None)  # the exported copies have none

    @property
    def group(self) -> Any:
        """The actor core's group (the CNN twin has none)."""
        return getattr(self.actor, "group", None)

    def forward(self, image: torch.Tensor, proprio: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        mean, _, features = self.actor(image, proprio)
        _, value, _ = self.critic(image, proprio)
        return mean, value, features

    def export_fast(self) -> nn.Module:
        """Both cores' plain-torch inference copies, paired the same way."""
        return SeparateCritic(self.actor.export_fast(), self.critic.export_fast()).eval().requires_grad_(False)
