"""The group-equivariant core (escnn): image + proprioception -> equivariant mean, invariant value.

Structure, for a group G (a subgroup of D4, see :mod:`covers_dist.symmetry`) and
``channels = [c_1, ..., c_n]``:

* image (3 trivial fields, S x S) -> n blocks of [R2Conv 3x3 (padding 1) to c_i regular fields,
  ReLU, 2x2 max-pool] -> an R2Conv whose kernel covers the remaining (S / 2^n)^2 map, to c_n
  regular fields at 1 x 1. 2x2 pooling of even sizes that halve evenly and the full-map kernel
  (sampled on grid points that G permutes) keep equivariance exact.
* proprio enters at 1 x 1 as fields: each planar pair transforms by the group's standard 2-D
  representation (:func:`covers_dist.symmetry.escnn_planar_repr`), the rest as trivial fields.
* fusion: [image fields (+) proprio fields] -> 1x1 R2Conv to ``hidden`` regular fields, ReLU,
  1x1 R2Conv to ``hidden`` regular fields, ReLU.
* policy mean: 1x1 R2Conv to ``action_pairs`` standard fields + ``action_scalars`` trivial ones;
  (dx, dy) rotate and mirror with the table, the rest is invariant.
* features: group pooling (max over each regular field) of the fused layer, ``hidden`` numbers,
  invariant; value: a linear map of the features.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from torch import nn

from ..envs.layout import ObsLayout
from ..symmetry import escnn_gspace, escnn_planar_repr, get_group
from ._escnn_compat import import_escnn_nn

__all__ = ["EquivariantCore"]

POLICY_HEAD_GAIN = 0.01


def _full_map_conv(enn: Any, in_type: Any, out_type: Any, size: int) -> Any:
    """An R2Conv whose ``size`` x ``size`` kernel covers the whole map (no padding) -> 1 x 1."""
    if size == 1:
        return enn.R2Conv(in_type, out_type, kernel_size=1)
    c = (size - 1) / 2.0
    radii = sorted({float(np.hypot(abs(i - c), abs(j - c))) for i in range(size) for j in range(size)})
    return enn.R2Conv(
        in_type,
        out_type,
        kernel_size=size,
        padding=0,
        rings=radii,
        sigma=[0.6] * len(radii),
        frequencies_cutoff=lambda r: 3.0,
    )


class EquivariantCore(nn.Module):
    """escnn feature extractor and heads; ``forward(image, proprio) -> (mean, value, features)``."""

    def __init__(self, layout: ObsLayout, group: str, channels: list[int], hidden: int) -> None:
        super().__init__()
        enn = import_escnn_nn()
        blocks = len(channels)
        if not channels or any(int(c) < 1 for c in channels):
            raise ValueError(f"channels must be a non-empty list of positive integers, got {channels!r}")
        if hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {hidden!r}")
        if layout.image_size % (2**blocks):
            raise ValueError(
                f"image_size={layout.image_size} must be divisible by 2**len(channels)={2**blocks} "
                "(each block halves the image exactly)"
            )
        self.layout = layout
        self.group = get_group(group)
        self.gspace = gs = escnn_gspace(self.group)
        regular, trivial, planar = gs.regular_repr, gs.trivial_repr, escnn_planar_repr(gs)

        self.in_type = enn.FieldType(gs, 3 * [trivial])
        layers: list[Any] = []
        prev = self.in_type
        for c in channels:
            out = enn.FieldType(gs, int(c) * [regular])
            layers += [enn.R2Conv(prev, out, kernel_size=3, padding=1), enn.ReLU(out), enn.PointwiseMaxPool2D(out, 2)]
            prev = out
        remaining = layout.image_size // (2**blocks)
        img_out = enn.FieldType(gs, int(channels[-1]) * [regular])
        layers += [_full_map_conv(enn, prev, img_out, remaining), enn.ReLU(img_out)]
        self.image_net = enn.SequentialModule(*layers)

        self.proprio_type = enn.FieldType(gs, layout.proprio_pairs * [planar] + layout.proprio_scalars * [trivial])
        fused_in = img_out + self.proprio_type
        self.hidden_type = enn.FieldType(gs, int(hidden) * [regular])
        self.fusion = enn.SequentialModule(
            enn.R2Conv(fused_in, self.hidden_type, kernel_size=1),
            enn.ReLU(self.hidden_type),
            enn.R2Conv(self.hidden_type, self.hidden_type, kernel_size=1),
            enn.ReLU(self.hidden_type),
        )
        self.action_type = enn.FieldType(gs, layout.action_pairs * [planar] + layout.action_scalars * [trivial])
        self.policy_head = enn.R2Conv(self.hidden_type, self.action_type, kernel_size=1)
        with torch.no_grad():
            self.policy_head.weights.mul_(POLICY_HEAD_GAIN)
            if self.policy_head.bias is not None:
                self.policy_head.bias.zero_()
        self.pool = enn.GroupPooling(self.hidden_type)
        self.feature_dim = int(hidden)
        self.value_head = nn.Linear(self.feature_dim, 1)

    def forward(self, image: torch.Tensor, proprio: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        from escnn.nn import GeometricTensor, tensor_directsum

        x = self.image_net(GeometricTensor(image, self.in_type))
        p = GeometricTensor(proprio[:, :, None, None], self.proprio_type)
        h = self.fusion(tensor_directsum([x, p]))
        mean = self.policy_head(h).tensor.flatten(1)
        features = self.pool(h).tensor.flatten(1)
        value = self.value_head(features).squeeze(-1)
        return mean, value, features

    def export_fast(self) -> nn.Module:
        """A plain-torch copy for no-grad inference (filters expanded once; the module's mode is untouched)."""
        with torch.no_grad():
            fast = _ExportedCore(
                _export(self.image_net),
                _export(self.fusion),
                _export(self.policy_head),
                _GroupMaxPool(self.pool.in_type.size // self.feature_dim),
                copy.deepcopy(self.value_head),
            )
        return fast.eval().requires_grad_(False)


def _export(module: Any) -> nn.Module:
    """Plain torch equivalent of an escnn module built by :class:`EquivariantCore`."""
    from escnn import nn as enn

    if isinstance(module, enn.SequentialModule):
        return nn.Sequential(*(_export(m) for m in module.children()))
    if isinstance(module, enn.R2Conv):
        weight, bias = module.expand_parameters()
        conv = nn.Conv2d(
            module.in_type.size,
            module.out_type.size,
            module.kernel_size,
            stride=module.stride,
            padding=module.padding,
            dilation=module.dilation,
            bias=bias is not None,
        )
        conv.weight.copy_(weight)
        if bias is not None:
            conv.bias.copy_(bias)
        return conv
    if isinstance(module, enn.ReLU):
        return nn.ReLU()
    if isinstance(module, enn.PointwiseMaxPool2D):
        return nn.MaxPool2d(module.kernel_size, module.stride, module.padding, module.dilation, module.ceil_mode)
    raise TypeError(f"no plain-torch export for {type(module).__name__}")


class _GroupMaxPool(nn.Module):
    """Max over each regular field's ``order`` channels (escnn ``GroupPooling``)."""

    def __init__(self, order: int) -> None:
        super().__init__()
        self.order = order

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        return x.view(b, c // self.order, self.order, h, w).amax(dim=2)


class _ExportedCore(nn.Module):
    def __init__(self, image_net: nn.Module, fusion: nn.Module, policy: nn.Module, pool: nn.Module, value: nn.Module):
        super().__init__()
        self.image_net, self.fusion, self.policy, self.pool, self.value = image_net, fusion, policy, pool, value

    def forward(self, image: torch.Tensor, proprio: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = self.image_net(image)
        h = self.fusion(torch.cat([x, proprio[:, :, None, None]], dim=1))
        mean = self.policy(h).flatten(1)
        features = self.pool(h).flatten(1)
        return mean, self.value(features).squeeze(-1), features
