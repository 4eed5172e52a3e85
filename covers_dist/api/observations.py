"""Decoding JSON observations (:class:`~.schemas.Observation`) into the numpy batch contract.

Every problem raises :class:`ObservationError` (a ``ValueError``) whose message names the
observation, the field and what was expected; the app answers it with 422.
"""

from __future__ import annotations

import base64
import binascii
import io
from typing import Sequence

import numpy as np

from ..envs.layout import ObsLayout
from .schemas import ArrayImage, Observation, PngImage

__all__ = ["ObservationError", "decode_observations", "encode_png", "observation_json"]


class ObservationError(ValueError):
    """A posted observation does not fit the run's observation layout."""


def _png(image: PngImage, size: int, where: str) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        raw = base64.b64decode(image.png_base64, validate=True)
    except (binascii.Error, ValueError) as e:
        raise ObservationError(f"{where}.png_base64 is not valid base64 ({e})") from None
    if not raw.startswith(b"\x89PNG\r\n\x1a\n"):
        raise ObservationError(f"{where}.png_base64 does not hold a PNG file (bad signature)")
    try:
        with Image.open(io.BytesIO(raw), formats=["PNG"]) as img:
            if img.size != (size, size):  # checked before decoding any pixel data
                raise ObservationError(f"{where}: PNG is {img.size[0]}x{img.size[1]} pixels, expected {size}x{size}")
            array = np.asarray(img.convert("RGB"), dtype=np.uint8)
    except ObservationError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise ObservationError(f"{where}.png_base64 is not a readable PNG ({e})") from None
    return array


def _array(image: ArrayImage, size: int, where: str) -> np.ndarray:
    expected = [size, size, 3]
    if list(image.shape) != expected:
        raise ObservationError(f"{where}.shape is {image.shape}, expected {expected}")
    if len(image.data) != size * size * 3:
        n = size * size * 3
        raise ObservationError(f"{where}.data has {len(image.data)} values, expected {n} (= {size}*{size}*3)")
    return np.asarray(image.data, dtype=np.uint8).reshape(size, size, 3)


def decode_observations(observations: Sequence[Observation], layout: ObsLayout) -> dict[str, np.ndarray]:
    """``{"image": uint8 (n, S, S, 3), "proprio": float32 (n, P)}`` from posted observations."""
    if not observations:
        raise ObservationError("at least one observation is needed")
    size, p = layout.image_size, layout.proprio_dim
    images = np.empty((len(observations), size, size, 3), dtype=np.uint8)
    proprio = np.empty((len(observations), p), dtype=np.float32)
    for i, obs in enumerate(observations):
        where = f"observation {i}: image"
        if isinstance(obs.image, PngImage):
            images[i] = _png(obs.image, size, where)
        else:
            images[i] = _array(obs.image, size, where)
        if len(obs.proprio) != p:
            raise ObservationError(f"observation {i}: proprio has {len(obs.proprio)} values, expected {p}")
        values = np.asarray(obs.proprio, dtype=np.float64)
        if not np.all(np.abs(values) <= np.finfo(np.float32).max):
            raise ObservationError(f"observation {i}: proprio values must fit in float32")
        proprio[i] = values
    return {"image": images, "proprio": proprio}


def encode_png(image: np.ndarray) -> str:
    """Base64 PNG of a uint8 (S, S, 3) image: the ``png_base64`` a client sends."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8)).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def observation_json(image: np.ndarray, proprio: np.ndarray, png: bool = True) -> dict:
    """The JSON form of one observation (what a client posts), from numpy arrays."""
    img = np.asarray(image, dtype=np.uint8)
    if png:
        image_json: dict = {"png_base64": encode_png(img)}
    else:
        image_json = {"shape": list(img.shape), "data": img.reshape(-1).tolist()}
    return {"image": image_json, "proprio": [float(x) for x in np.asarray(proprio).reshape(-1)]}
