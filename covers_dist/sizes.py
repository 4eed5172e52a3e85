"""Map sizes of the conv blocks: plain arithmetic shared by the config checks and the networks.

Imports nothing (no torch, no escnn): :mod:`covers_dist.config` validates ``env.image_size``,
``network.channels`` and ``network.space_to_depth`` with it, and both cores
(:mod:`covers_dist.models.equivariant`, :mod:`covers_dist.models.cnn`) lay out their blocks by it.
It lives outside :mod:`covers_dist.models` because importing any module of that package runs
its ``__init__``, which imports torch.
"""

from __future__ import annotations

__all__ = ["block_sizes"]


def block_sizes(image_size: int, blocks: int, space_to_depth: int = 1) -> tuple[list[int], int]:
    """Map side entering each conv block, and the side left for the full-map convolution.

    The map starts at ``image_size / space_to_depth``; each block halves it while it is above 1.
    Raises ``ValueError`` when a block would pool an odd map (equivariance needs exact halving).
    """
    if space_to_depth < 1 or image_size % space_to_depth:
        raise ValueError(f"image_size={image_size} must be divisible by space_to_depth={space_to_depth}")
    size, sizes = image_size // space_to_depth, []
    for i in range(blocks):
        sizes.append(size)
        if size > 1:
            if size % 2:
                raise ValueError(
                    f"image_size={image_size} with space_to_depth={space_to_depth}: conv block {i + 1} of {blocks} "
                    f"would pool a {size} x {size} map (each block halves the map exactly; "
                    f"image_size / space_to_depth must be divisible by 2**len(channels) or reach 1 x 1)"
                )
            size //= 2
    return sizes, size
