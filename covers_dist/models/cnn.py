"""The plain-CNN twin of the equivariant core (for the CNN and COVERS-CNN baselines).

Same layout as :class:`covers_dist.models.equivariant.EquivariantCore`, with ordinary layers:
the same optional space-to-depth stem (:class:`torch.nn.PixelUnshuffle`), n blocks of [Conv 3x3
(padding 1), ReLU, 2x2 max-pool] (a 1x1 conv once the map is 1 x 1), a convolution covering the
remaining map down to 1 x 1, then [image features, proprio] -> Linear -> ReLU -> Linear -> ReLU (the features)
-> linear policy mean and value heads. Widths are the equivariant net's field counts times
``width`` (by default sqrt(|G|), which gives a similar parameter count: a regular-field
convolution has about |G| times fewer free parameters than a plain one with |G| times the
channels). Nothing here is constrained, so the twin is not invariant to rotations or mirrors.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from ..envs.layout import ObsLayout
from ..sizes import block_sizes

__all__ = ["CNNCore"]

POLICY_HEAD_GAIN = 0.01


class CNNCore(nn.Module):
    """Plain CNN feature extractor and heads; ``forward(image, proprio) -> (mean, value, features)``."""

    def __init__(
        self, layout: ObsLayout, channels: list[int], hidden: int, width: float, space_to_depth: int = 1
    ) -> None:
        super().__init__()
        if not channels or any(int(c) < 1 for c in channels):
            raise ValueError(f"channels must be a non-empty list of positive integers, got {channels!r}")
        if width <= 0:
            raise ValueError(f"width must be > 0, got {width!r}")
        sizes, remaining = block_sizes(layout.image_size, len(channels), space_to_depth)
        self.layout = layout
        widths = [max(1, round(c * width)) for c in channels]
        layers: list[nn.Module] = [nn.PixelUnshuffle(space_to_depth)] if space_to_depth > 1 else []
        prev = 3 * space_to_depth**2
        for w, size in zip(widths, sizes):
            if size > 1:
                layers += [nn.Conv2d(prev, w, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2)]
            else:
                layers += [nn.Conv2d(prev, w, 1), nn.ReLU()]
            prev = w
        layers += [nn.Conv2d(prev, widths[-1], remaining), nn.ReLU(), nn.Flatten(1)]
        self.image_net = nn.Sequential(*layers)
        h = max(1, round(hidden * width))
        self.fusion = nn.Sequential(
            nn.Linear(widths[-1] + layout.proprio_dim, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU()
        )
        self.policy_head = nn.Linear(h, layout.action_dim)
        with torch.no_grad():
            self.policy_head.weight.mul_(POLICY_HEAD_GAIN)
            self.policy_head.bias.zero_()
        self.value_head = nn.Linear(h, 1)
        self.feature_dim = h
        self.widths = widths

    def forward(self, image: torch.Tensor, proprio: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = self.image_net(image)
        features = self.fusion(torch.cat([x, proprio], dim=1))
        return self.policy_head(features), self.value_head(features).squeeze(-1), features

    def export_fast(self) -> nn.Module:
        """A detached eval-mode copy for no-grad inference."""
        return copy.deepcopy(self).eval().requires_grad_(False)
