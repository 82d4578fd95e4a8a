"""Contact sheets: every camera of a frame in one labelled grid image."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np


def contact_sheet(
    images: Sequence[np.ndarray],
    labels: Sequence[str] | None = None,
    *,
    columns: int | None = None,
    pad: int = 4,
    label_height: int = 14,
    background: int = 32,
) -> np.ndarray:
    """Tile images into a grid, each with its label (e.g. the camera name) above it.

    Args:
        images: N uint8 images [H_i, W_i, 3] (or [H_i, W_i] grey); sizes may differ, each cell
            is as large as the largest image and images sit at the cell's top-left.
        labels: N strings drawn with PIL's default bitmap font, or None for no labels.
        columns: grid width; default ceil(sqrt(N)) so the sheet is roughly square.
        pad: pixels between cells and around the border.
        label_height: pixels reserved above each image for its label (0 with no labels).
        background: grey level of the gaps.
    Returns:
        [H', W', 3] uint8 sheet.
    """
    from PIL import Image, ImageDraw, ImageFont

    if len(images) == 0:
        raise ValueError("contact_sheet needs at least one image")
    if labels is not None and len(labels) != len(images):
        raise ValueError(f"{len(images)} images but {len(labels)} labels")
    tiles = []
    for img in images:
        a = np.asarray(img)
        if a.dtype != np.uint8:
            raise TypeError(f"contact_sheet expects uint8 images, got {a.dtype}")
        if a.ndim == 2:
            a = np.repeat(a[..., None], 3, axis=2)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"contact_sheet expects [H, W, 3] or [H, W] images, got {a.shape}")
        tiles.append(a)
    n = len(tiles)
    cols = columns or math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    th = max(t.shape[0] for t in tiles)
    tw = max(t.shape[1] for t in tiles)
    lh = label_height if labels is not None else 0
    cell_h, cell_w = lh + th, tw
    H = pad + rows * (cell_h + pad)
    W = pad + cols * (cell_w + pad)
    sheet = np.full((H, W, 3), background, dtype=np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        y0, x0 = pad + r * (cell_h + pad) + lh, pad + c * (cell_w + pad)
        sheet[y0 : y0 + t.shape[0], x0 : x0 + t.shape[1]] = t
    if labels is not None:
        canvas = Image.fromarray(sheet)
        draw = ImageDraw.Draw(canvas)
        font = ImageFont.load_default()
        for i, label in enumerate(labels):
            r, c = divmod(i, cols)
            x0, y0 = pad + c * (cell_w + pad), pad + r * (cell_h + pad)
            # Clip long names to the cell so they do not run into the neighbour's label.
            text = str(label)
            while text and draw.textlength(text, font=font) > cell_w:
                text = text[:-1]
            draw.text((x0 + 1, y0 + 1), text, fill=(255, 255, 255), font=font)
        sheet = np.asarray(canvas).copy()
    return sheet
