"""How observations and actions are laid out, and how the symmetry group acts on them.

Every task in covers-dist (toy or Meta-World) returns observations ``{"image": uint8 (S, S, 3),
"proprio": float32 (P,)}`` and takes float32 actions of shape (A,). Vectors follow one rule:
the first ``2 * pairs`` entries are planar ``(x, y)`` pairs, which rotate and mirror with the
table; the remaining entries (heights, gripper opening, ...) are invariant. Networks read the
same layout to build their equivariant input and output types.

A layout may also carry fixed input statistics of its proprio (``proprio_shift``,
``proprio_scale``): networks built with ``network.proprio_norm`` feed ``(proprio - shift) * scale``.
Planar pairs take one scale for both entries and no shift, so the map commutes with every rotation
and mirror and the networks stay exactly equivariant; invariant entries may take any shift and scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..symmetry import GroupElement

__all__ = ["ObsLayout", "transform_obs"]


@dataclass(frozen=True)
class ObsLayout:
    """Shapes and transformation laws of a task family's observations and actions."""

    image_size: int
    proprio_dim: int
    proprio_pairs: int
    action_dim: int
    action_pairs: int
    #: fixed proprio statistics, one entry per proprio entry; empty: none (identity)
    proprio_shift: tuple[float, ...] = ()
    proprio_scale: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if 2 * self.proprio_pairs > self.proprio_dim:
            raise ValueError(f"proprio_dim={self.proprio_dim} cannot hold {self.proprio_pairs} planar pairs")
        if 2 * self.action_pairs > self.action_dim:
            raise ValueError(f"action_dim={self.action_dim} cannot hold {self.action_pairs} planar pairs")
        shift, scale = tuple(self.proprio_shift), tuple(self.proprio_scale)
        if not shift and not scale:
            return
        if len(shift) != self.proprio_dim or len(scale) != self.proprio_dim:
            raise ValueError(
                f"proprio_shift and proprio_scale need {self.proprio_dim} entries each, got {len(shift)} and {len(scale)}"
            )
        if not all(math.isfinite(v) for v in shift) or not all(math.isfinite(v) and v > 0 for v in scale):
            raise ValueError(f"proprio_shift must be finite and proprio_scale finite and > 0, got {shift}, {scale}")
        for i in range(self.proprio_pairs):
            x, y = 2 * i, 2 * i + 1
            if shift[x] != 0.0 or shift[y] != 0.0 or scale[x] != scale[y]:
                raise ValueError(
                    f"planar pair {i} (proprio entries {x}, {y}) needs shift 0 and one scale for both entries "
                    f"(a rotation must commute with the normalisation), got shift {shift[x:y + 1]}, scale {scale[x:y + 1]}"
                )

    @property
    def has_proprio_stats(self) -> bool:
        return bool(self.proprio_scale)

    @property
    def proprio_scalars(self) -> int:
        return self.proprio_dim - 2 * self.proprio_pairs

    @property
    def action_scalars(self) -> int:
        return self.action_dim - 2 * self.action_pairs

    def transform_proprio(self, g: GroupElement, proprio: np.ndarray) -> np.ndarray:
        return g.apply_planar(proprio, self.proprio_pairs)

    def transform_action(self, g: GroupElement, action: np.ndarray) -> np.ndarray:
        return g.apply_planar(action, self.action_pairs)


def transform_obs(layout: ObsLayout, g: GroupElement, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``g`` applied to one observation dict, or to a batch (image (B, S, S, 3), proprio (B, P))."""
    image = np.asarray(obs["image"])
    img = g.apply_images(image) if image.ndim == 4 else g.apply_image(image)
    return {"image": img, "proprio": layout.transform_proprio(g, obs["proprio"])}
