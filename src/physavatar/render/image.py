"""Image conversions and atomic image files.

Renders are linear radiance; files on disk (captures, contact sheets) are sRGB-encoded 8-bit PNGs
as DESIGN.md's capture format says. The sRGB transfer function is the piecewise IEC 61966-2-1
curve, not a plain 2.2 gamma, so that ``srgb_to_linear(linear_to_srgb(x)) == x``.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values -> sRGB-encoded values, both float in [0, 1] (input clipped to [0, 1])."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear values in [0, 1]."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def to_uint8(x: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] -> uint8 with round-to-nearest (values outside are clipped)."""
    return np.clip(np.rint(np.asarray(x, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] linear float -> [H, W, 3] sRGB uint8 (the encoding of capture images)."""
    return to_uint8(linear_to_srgb(rgb))


def alpha_to_uint8(alpha: np.ndarray) -> np.ndarray:
    """[H, W] coverage in [0, 1] -> [H, W] uint8 mask (linear, no transfer curve)."""
    return to_uint8(alpha)


def write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write a uint8 [H, W], [H, W, 3] or [H, W, 4] image to ``path`` atomically.

    The PNG is written to a temporary file in the same folder and renamed over ``path``, so a
    reader (or an interrupted run, DESIGN.md) never sees a half-written file.
    """
    from PIL import Image

    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise TypeError(f"write_png expects uint8, got {img.dtype} (convert with linear_to_srgb8)")
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (3, 4))):
        raise ValueError(f"write_png expects [H, W], [H, W, 3] or [H, W, 4], got {img.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            Image.fromarray(np.ascontiguousarray(img)).save(f, format="PNG")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def read_png(path: str | os.PathLike) -> np.ndarray:
    """uint8 array of a PNG as stored ([H, W] or [H, W, C])."""
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im).copy()
