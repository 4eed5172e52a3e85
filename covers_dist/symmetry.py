"""The symmetry core: the dihedral group D4 and its subgroups acting on the table plane.

One convention, shared by the environments and the networks:

* Planar coordinates: ``x`` points right, ``y`` points up, both measured from the symmetry
  centre. In a square top-down image of shape (H, W, ...) the pixel at row ``i``, column ``j``
  sits at ``(x, y) = (j - c, c - i)`` with ``c = (H - 1) / 2``.
* ``r`` is the rotation by +90 degrees (counter-clockwise): ``(x, y) -> (-y, x)``.
  On an image it is ``np.rot90(img, 1)``.
* ``f`` is the mirror about the vertical axis: ``(x, y) -> (-x, y)``.
  On an image it is a left-right flip.
* The element ``(k, m)`` (``k`` in 0..3, ``m`` in {0, 1}) is ``r^k f^m``: mirror first (if ``m``),
  then rotate by ``k`` quarter turns. Its 2x2 matrix is ``R^k F^m``.

An element acts on images by moving their content: ``(g.img)(p) = img(g^-1 p)``, so that drawing
a point at ``p`` and then transforming the image equals drawing it at ``g p``
(tests check this pixel for pixel).

Subgroups are named as in escnn: ``D4``, ``C4``, ``D2`` ({e, r^2, f, r^2 f}), ``C2`` ({e, r^2}),
``D1`` (the single mirror {e, f}) and ``trivial``. :func:`escnn_gspace` and
:func:`to_escnn_element` map them to escnn so that an escnn ``GeometricTensor.transform(e)``
moves an image exactly as :meth:`GroupElement.apply_image` does, and escnn's
action on the plane (``gspace.basespace_action``, see :func:`escnn_planar_repr`) of ``e`` equals
:meth:`GroupElement.matrix`.

This module imports numpy only; torch and escnn are imported lazily where needed.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = [
    "GroupElement",
    "SymmetryGroup",
    "GROUP_NAMES",
    "get_group",
    "D4_ELEMENTS",
    "escnn_gspace",
    "to_escnn_element",
    "escnn_planar_repr",
]

_R = np.array([[0, -1], [1, 0]], dtype=np.int64)
_F = np.array([[-1, 0], [0, 1]], dtype=np.int64)


@dataclass(frozen=True, order=True)
class GroupElement:
    """The element ``r^k f^m`` of D4 (``k`` quarter turns after ``m`` mirrors)."""

    k: int = 0
    m: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.k, (int, np.integer)) or not isinstance(self.m, (int, np.integer)):
            raise TypeError(f"GroupElement needs integers, got k={self.k!r}, m={self.m!r}")
        if not 0 <= self.k <= 3 or self.m not in (0, 1):
            raise ValueError(f"GroupElement needs k in 0..3 and m in {{0, 1}}, got k={self.k}, m={self.m}")
        object.__setattr__(self, "k", int(self.k))
        object.__setattr__(self, "m", int(self.m))

    # ---- group structure -------------------------------------------------------------------
    def __mul__(self, other: "GroupElement") -> "GroupElement":
        """Composition ``self * other`` (apply ``other`` first, then ``self``)."""
        if not isinstance(other, GroupElement):
            return NotImplemented
        # r^k1 f^m1 r^k2 f^m2 = r^(k1 + (-1)^m1 k2) f^(m1 + m2)
        sign = -1 if self.m else 1
        return GroupElement((self.k + sign * other.k) % 4, (self.m + other.m) % 2)

    def inverse(self) -> "GroupElement":
        if self.m:
            return self  # every reflection is an involution
        return GroupElement((-self.k) % 4, 0)

    @property
    def is_identity(self) -> bool:
        return self.k == 0 and self.m == 0

    @property
    def name(self) -> str:
        """Short readable name: ``e``, ``r``, ``r2``, ``r3``, ``f``, ``rf``, ``r2f``, ``r3f``."""
        if self.is_identity:
            return "e"
        rot = "" if self.k == 0 else ("r" if self.k == 1 else f"r{self.k}")
        return rot + ("f" if self.m else "")

    @property
    def index(self) -> int:
        """Position in :data:`D4_ELEMENTS` (0..7): rotations first, then reflections."""
        return self.m * 4 + self.k

    @classmethod
    def from_name(cls, name: str) -> "GroupElement":
        for g in D4_ELEMENTS:
            if g.name == name:
                return g
        raise ValueError(f"unknown D4 element name {name!r}; expected one of {[g.name for g in D4_ELEMENTS]}")

    def __repr__(self) -> str:
        return f"GroupElement({self.name})"

    # ---- actions ---------------------------------------------------------------------------
    def matrix(self) -> np.ndarray:
        """The 2x2 integer matrix ``R^k F^m`` acting on column vectors ``(x, y)``."""
        return _matrix(self.k, self.m).copy()

    def apply_vectors(self, v: np.ndarray) -> np.ndarray:
        """Act on planar vectors: ``v`` has shape (..., 2) holding ``(x, y)`` pairs.

        Uses only swaps and sign changes, so the result is exact in floating point.
        """
        v = np.asarray(v)
        if v.shape[-1:] != (2,):
            raise ValueError(f"apply_vectors expects shape (..., 2), got {v.shape}")
        x, y = v[..., 0], v[..., 1]
        if self.m:
            x = -x
        for _ in range(self.k):
            x, y = -y, x
        return np.stack([x, y], axis=-1).astype(v.dtype, copy=False)

    def apply_planar(self, vec: np.ndarray, num_pairs: int) -> np.ndarray:
        """Act on a flat vector whose first ``2 * num_pairs`` entries are (x, y) pairs.

        The remaining entries (z, gripper, ...) are invariant and copied unchanged. Works on
        batches of shape (..., D).
        """
        vec = np.asarray(vec)
        if vec.shape[-1] < 2 * num_pairs:
            raise ValueError(f"vector of length {vec.shape[-1]} cannot hold {num_pairs} planar pairs")
        out = vec.copy()
        if num_pairs:
            pairs = vec[..., : 2 * num_pairs].reshape(*vec.shape[:-1], num_pairs, 2)
            out[..., : 2 * num_pairs] = self.apply_vectors(pairs).reshape(*vec.shape[:-1], 2 * num_pairs)
        return out

    def apply_image(self, img: np.ndarray) -> np.ndarray:
        """Act on a square image of shape (H, W) or (H, W, C); returns a contiguous copy."""
        img = np.asarray(img)
        if img.ndim not in (2, 3) or img.shape[0] != img.shape[1]:
            raise ValueError(f"apply_image expects a square (H, W) or (H, W, C) image, got {img.shape}")
        out = img[:, ::-1] if self.m else img
        if self.k:
            out = np.rot90(out, self.k, axes=(0, 1))
        return np.ascontiguousarray(out)

    def apply_images(self, imgs: np.ndarray) -> np.ndarray:
        """Act on a batch of square images of shape (B, H, W, C)."""
        imgs = np.asarray(imgs)
        if imgs.ndim != 4 or imgs.shape[1] != imgs.shape[2]:
            raise ValueError(f"apply_images expects (B, H, W, C) with H == W, got {imgs.shape}")
        out = imgs[:, :, ::-1] if self.m else imgs
        if self.k:
            out = np.rot90(out, self.k, axes=(1, 2))
        return np.ascontiguousarray(out)

    def apply_tensor(self, x: "torch.Tensor") -> "torch.Tensor":
        """Act on a batched torch tensor of shape (B, C, H, W) (channels first)."""
        import torch

        if x.dim() != 4 or x.shape[-1] != x.shape[-2]:
            raise ValueError(f"apply_tensor expects (B, C, H, W) with H == W, got {tuple(x.shape)}")
        out = torch.flip(x, dims=(3,)) if self.m else x
        if self.k:
            out = torch.rot90(out, self.k, dims=(2, 3))
        return out


@lru_cache(maxsize=None)
def _matrix(k: int, m: int) -> np.ndarray:
    mat = np.linalg.matrix_power(_R, k) @ (_F if m else np.eye(2, dtype=np.int64))
    mat.setflags(write=False)
    return mat


D4_ELEMENTS: tuple[GroupElement, ...] = tuple(GroupElement(k, m) for m in (0, 1) for k in range(4))

_SUBGROUPS: dict[str, tuple[GroupElement, ...]] = {
    "D4": D4_ELEMENTS,
    "C4": tuple(GroupElement(k, 0) for k in range(4)),
    "D2": (GroupElement(0, 0), GroupElement(2, 0), GroupElement(0, 1), GroupElement(2, 1)),
    "C2": (GroupElement(0, 0), GroupElement(2, 0)),
    "D1": (GroupElement(0, 0), GroupElement(0, 1)),
    "trivial": (GroupElement(0, 0),),
}
_ALIASES = {"flip": "D1", "mirror": "D1", "c1": "trivial", "none": "trivial", "e": "trivial"}
GROUP_NAMES: tuple[str, ...] = tuple(_SUBGROUPS)


@dataclass(frozen=True)
class SymmetryGroup:
    """A subgroup of D4, by name (``D4``, ``C4``, ``D2``, ``C2``, ``D1``, ``trivial``)."""

    name: str
    elements: tuple[GroupElement, ...]

    def __iter__(self) -> Iterator[GroupElement]:
        return iter(self.elements)

    def __len__(self) -> int:
        return len(self.elements)

    def __contains__(self, g: object) -> bool:
        return g in self.elements

    @property
    def order(self) -> int:
        return len(self.elements)

    @property
    def has_reflections(self) -> bool:
        return any(g.m for g in self.elements)

    @property
    def rotation_order(self) -> int:
        """Number of rotations in the group (N of escnn's C_N / D_N)."""
        return sum(1 for g in self.elements if not g.m)


def get_group(name: str) -> SymmetryGroup:
    """The subgroup of D4 called ``name`` (case-insensitive; ``flip``/``mirror`` mean ``D1``)."""
    if not isinstance(name, str):
        raise TypeError(f"group name must be a string, got {type(name).__name__}")
    key = _ALIASES.get(name.lower(), name)
    for known in _SUBGROUPS:
        if known.lower() == key.lower():
            return SymmetryGroup(known, _SUBGROUPS[known])
    raise ValueError(f"unknown symmetry group {name!r}; expected one of {list(GROUP_NAMES)}")


# ---- escnn bridge --------------------------------------------------------------------------
def escnn_gspace(group: str | SymmetryGroup) -> Any:
    """The escnn gspace on R^2 for ``group`` (imports escnn lazily).

    Mirrors use escnn's reflection axis ``pi / 2`` (the vertical axis), which is this module's
    ``f``; tests check that images and standard representations agree element by element.
    """
    grp = get_group(group) if isinstance(group, str) else group
    gspaces = _import_escnn_gspaces()
    n = grp.rotation_order
    if grp.name == "trivial":
        return gspaces.trivialOnR2()
    if grp.has_reflections:
        if n == 1:
            return gspaces.flip2dOnR2(axis=np.pi / 2)
        return gspaces.flipRot2dOnR2(N=n, axis=np.pi / 2)
    return gspaces.rot2dOnR2(N=n)


def to_escnn_element(g: GroupElement, gspace: Any) -> Any:
    """The element of ``gspace.fibergroup`` that acts like ``g`` (``g`` must be in the group)."""
    group = gspace.fibergroup
    name = type(group).__name__
    if getattr(gspace, "flips_order", 0) and getattr(gspace, "rotations_order", 0) == 1:
        # the single-mirror gspace: escnn models {e, f} as the cyclic group of order 2
        if g.k:
            raise ValueError(f"{g} is not in the mirror group D1")
        return group.element(g.m, param="int")
    if name == "CyclicGroup":
        n = group.order()
        if g.m or (g.k * n) % 4:
            raise ValueError(f"{g} is not in the cyclic group C{n}")
        return group.element(g.k * n // 4, param="int")
    if name == "DihedralGroup":
        n = group.order() // 2
        if (g.k * n) % 4:
            raise ValueError(f"{g} is not in the dihedral group D{n}")
        return group.element((g.m, g.k * n // 4), param="int")
    raise ValueError(f"unsupported escnn fibre group {name}")


def escnn_planar_repr(gspace: Any) -> Any:
    """The escnn representation under which planar (x, y) vectors transform.

    It is ``gspace.basespace_action``; its matrix for ``to_escnn_element(g)`` equals
    ``g.matrix()`` (tests check every element), so (dx, dy) heads and proprio inputs use it.
    """
    return gspace.basespace_action


def _import_escnn_gspaces() -> Any:
    from ._imports import import_lightly

    return import_lightly("escnn.gspaces")
