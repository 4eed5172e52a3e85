"""The group-equivariant core (escnn): image + proprioception -> equivariant mean, invariant value.

Structure, for a group G (a subgroup of D4, see :mod:`covers_dist.symmetry`) and
``channels = [c_1, ..., c_n]``:

* image (3 trivial fields, S x S) -> optional space-to-depth stem (``space_to_depth = k``: each
  k x k block of pixels becomes k^2 channels per colour, a map k times smaller; see below) ->
  n blocks of [R2Conv 3x3 (padding 1) to c_i regular fields, ReLU, 2x2 max-pool] (blocks that
  meet a 1 x 1 map use a 1x1 R2Conv and no pooling) -> an R2Conv whose kernel covers the remaining
  map, to c_n regular fields at 1 x 1. 2x2 pooling of even sizes and the full-map kernel (sampled
  on grid points that G permutes) keep equivariance exact.
* the space-to-depth stem is lossless and exactly equivariant: a rotation or mirror of the table
  moves each k x k block to its image block and permutes the k^2 pixels inside it the same way
  for every block, so the k^2 channels of a colour form one field of that permutation
  representation (:func:`space_to_depth_repr`; e.g. k = 2: D4 permuting the corners of a square).
  Every block then runs on a map k times smaller, about k^2 times fewer FLOPs.
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
from torch.nn import functional as F

from ..envs.layout import ObsLayout
from ..sizes import block_sizes
from ..symmetry import escnn_gspace, escnn_planar_repr, get_group
from ._escnn_compat import import_escnn_nn

__all__ = ["EquivariantCore", "block_sizes", "canonical_change_of_basis", "space_to_depth_repr"]

POLICY_HEAD_GAIN = 0.01
_S2D_REPRS: dict[tuple[str, int], Any] = {}  # one representation per (gspace, k), built once


def space_to_depth_repr(gspace: Any, k: int) -> Any:
    """The representation of ``gspace``'s group on the k^2 pixels of a k x k block (channel order of
    :func:`torch.nn.functional.pixel_unshuffle`: row-major within the block).

    Built from escnn's own action on a k x k grid, so it matches how escnn moves the map. Its
    change of basis into irreps is :func:`canonical_change_of_basis`, the same in every process:
    escnn's own decomposition (``build_from_discrete_group_representation``) starts an optimiser
    from numpy's global random state, so two processes (a learner and a rollout worker) would read
    the same weights of the first convolution as different filters.
    """
    enn = import_escnn_nn()
    from escnn.group import Representation

    FieldType = enn.FieldType
    group = gspace.fibergroup
    key = (repr(gspace), k)
    if key in _S2D_REPRS:
        return _S2D_REPRS[key]
    grid = torch.arange(k * k, dtype=torch.float64).view(1, 1, k, k)
    trivial = FieldType(gspace, [gspace.trivial_repr])
    matrices = {}
    for h in group.elements:
        moved = trivial.transform(grid, h).round().long().flatten().tolist()
        if sorted(moved) != list(range(k * k)):
            raise RuntimeError(f"escnn's action of {h} on a {k} x {k} grid is not a permutation")
        perm = np.zeros((k * k, k * k))
        perm[np.arange(k * k), moved] = 1.0  # (g . x)[p] = x[moved[p]]
        matrices[h] = perm
    irreps, cob = canonical_change_of_basis(matrices, group)
    name = f"space_to_depth_{k}_canonical"
    rep = group.representations.get(name)
    if rep is None:
        rep = Representation(group, name, irreps, cob, ["pointwise"], representation=matrices)
    _S2D_REPRS[key] = rep
    return rep


def canonical_change_of_basis(matrices: dict[Any, np.ndarray], group: Any) -> tuple[list[tuple], np.ndarray]:
    """``(irreps, Q)`` with ``matrices[g] = Q @ (direct sum of irreps)(g) @ Q.T`` for every element,
    ``Q`` orthogonal, computed without randomness (so every process gets the same ``Q``).

    Irreps come in escnn's order (its character-based multiplicities). For each irrep psi of
    multiplicity m, the columns of one copy are the group average ``T = sum_g rho(g) A psi(g)^T``
    (an intertwiner for any ``A``) for the fixed candidates ``A = e_i e_j^T`` in order, minus its
    projection on the copies already taken, scaled by ``(T^T T)^(-1/2)`` (which commutes with psi,
    so ``T`` stays an intertwiner and becomes an isometry); candidates with nothing left are skipped.
    """
    from escnn.group._numerical import find_irreps_multiplicities_finitegroup

    elements = list(group.elements)
    n = next(iter(matrices.values())).shape[0]
    irreps: list[tuple] = []
    blocks: list[np.ndarray] = []
    for irrep_id, mult in find_irreps_multiplicities_finitegroup(matrices, group):
        psi = group.irrep(*irrep_id)
        d = psi.size
        psis = [np.asarray(psi(g), dtype=np.float64) for g in elements]
        taken: list[np.ndarray] = []
        for i in range(n):
            for j in range(d):
                if len(taken) == mult:
                    break
                t = sum(np.outer(matrices[g][:, i], p[:, j]) for g, p in zip(elements, psis)) / len(elements)
                for prev in blocks + taken:  # other irreps' copies are orthogonal already; this is exact
                    t = t - prev @ (prev.T @ t)
                gram = t.T @ t
                w, v = np.linalg.eigh(gram)
                if w.min() < 1e-8:
                    continue
                taken.append(t @ (v @ np.diag(w**-0.5) @ v.T))
        if len(taken) != mult:
            raise RuntimeError(f"found {len(taken)} of {mult} copies of irrep {irrep_id} in a {n}-dim representation")
        blocks += taken
        irreps += [tuple(irrep_id)] * mult
    q = np.concatenate(blocks, axis=1)
    if q.shape != (n, n) or not np.allclose(q.T @ q, np.eye(n), atol=1e-9):
        raise RuntimeError("the canonical change of basis is not orthogonal")
    for g in elements:
        diag = _block_diag([np.asarray(group.irrep(*i)(g), dtype=np.float64) for i in irreps])
        if not np.allclose(matrices[g], q @ diag @ q.T, atol=1e-9):
            raise RuntimeError(f"the canonical change of basis does not decompose the representation at {g}")
    return irreps, q


def _block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    size = sum(b.shape[0] for b in blocks)
    out, at = np.zeros((size, size)), 0
    for b in blocks:
        out[at : at + b.shape[0], at : at + b.shape[0]] = b
        at += b.shape[0]
    return out


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

    def __init__(
        self, layout: ObsLayout, group: str, channels: list[int], hidden: int, space_to_depth: int = 1
    ) -> None:
        super().__init__()
        enn = import_escnn_nn()
        if not channels or any(int(c) < 1 for c in channels):
            raise ValueError(f"channels must be a non-empty list of positive integers, got {channels!r}")
        if hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {hidden!r}")
        sizes, remaining = block_sizes(layout.image_size, len(channels), space_to_depth)
        self.layout = layout
        self.space_to_depth = int(space_to_depth)
        self.group = get_group(group)
        self.gspace = gs = escnn_gspace(self.group)
        regular, trivial, planar = gs.regular_repr, gs.trivial_repr, escnn_planar_repr(gs)

        k = self.space_to_depth
        pixel = space_to_depth_repr(gs, k) if k > 1 else trivial
        self.in_type = enn.FieldType(gs, 3 * [pixel])
        layers: list[Any] = []
        prev = self.in_type
        for c, size in zip(channels, sizes):
            out = enn.FieldType(gs, int(c) * [regular])
            if size > 1:
                layers += [enn.R2Conv(prev, out, kernel_size=3, padding=1), enn.ReLU(out), enn.PointwiseMaxPool2D(out, 2)]
            else:
                layers += [enn.R2Conv(prev, out, kernel_size=1), enn.ReLU(out)]
            prev = out
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

        if self.space_to_depth > 1:
            image = F.pixel_unshuffle(image, self.space_to_depth).contiguous(memory_format=torch.channels_last)
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
                _stem(self.space_to_depth, _export(self.image_net)),
                _export(self.fusion),
                _export(self.policy_head),
                _GroupMaxPool(self.pool.in_type.size // self.feature_dim),
                copy.deepcopy(self.value_head),
            )
        return fast.eval().requires_grad_(False)


def _stem(k: int, image_net: nn.Module) -> nn.Module:
    return nn.Sequential(nn.PixelUnshuffle(k), image_net) if k > 1 else image_net


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
