"""The images the flow runs on: grey and colour-opponent channels, dense optical flow at full or
reduced size, and whether a garment's colours carry a pattern.

The flow start (:mod:`.flow`) measures motion by OpenCV's DIS optical flow on single-channel
uint8 images. A texture whose pattern lies in its hues (a plaid of bands of similar brightness)
or that is aliased at the capture's resolution shows little in the luma; the colour-opponent
channels R - G and (R + G)/2 - B (at the luma's scale, so a plain colour stays as flat as in the
luma) and a flow at half size (coarse to fine) give the corrections something to lock on to.
"""

from __future__ import annotations

import numpy as np

from ...camera import Camera
from .raster import rasterize


def to_gray8(image: np.ndarray) -> np.ndarray:
    """[H, W] uint8 luma of an sRGB image [H, W, 3] in [0, 1] or uint8 (a [H, W] uint8 image is
    returned as is)."""
    if image.dtype == np.uint8 and image.ndim == 2:
        return image
    a = np.asarray(image, np.float64) / (255.0 if image.dtype == np.uint8 else 1.0)
    if a.ndim == 3:
        a = a[..., :3] @ np.array([0.299, 0.587, 0.114])
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)


def optical_flow(image0: np.ndarray, image1: np.ndarray, preset: str = "medium") -> np.ndarray:
    """[H, W, 2] dense flow (pixels, x then y) from ``image0`` to ``image1`` ([H, W, 3] sRGB in
    [0, 1] or [H, W] uint8), by OpenCV's DIS optical flow: image0[y, x] ~ image1[y + f_y, x + f_x]."""
    import cv2

    presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, "fine": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
    a, b = to_gray8(image0), to_gray8(image1)
    dis = cv2.DISOpticalFlow_create(presets[preset])
    if preset == "fine":
        # "medium" searches down to half resolution; the finest level roughly halves the flow
        # error of a swinging hem at ~5x the time
        dis.setFinestScale(0)
    return dis.calc(a, b, None).astype(np.float64)


def to_rgb8(image: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8 of an sRGB image [H, W, 3] in [0, 1] (uint8 images are returned as they are)."""
    if image.dtype == np.uint8:
        return image
    return np.clip(np.rint(np.asarray(image, np.float64)[..., :3] * 255.0), 0, 255).astype(np.uint8)


def opponent_channels(a: np.ndarray, b: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The colour-opponent channels R - G and (R + G)/2 - B of two sRGB uint8 images [H, W, 3], as
    uint8 pairs at the luma's scale (128 + the difference in sRGB levels, clipped): a plaid whose
    bands differ in hue more than in luma keeps its pattern there, and a plain colour stays as flat
    (and as noisy) as in the luma, not stretched to the range."""
    fa, fb = a.astype(np.float32), b.astype(np.float32)
    out = []
    for ca, cb in ((fa[..., 0] - fa[..., 1], fb[..., 0] - fb[..., 1]),
                   (0.5 * (fa[..., 0] + fa[..., 1]) - fa[..., 2], 0.5 * (fb[..., 0] + fb[..., 1]) - fb[..., 2])):
        out.append(tuple(np.clip(np.rint(128.0 + c), 0, 255).astype(np.uint8) for c in (ca, cb)))
    return out


def image_channels(a: np.ndarray, b: np.ndarray, channels: str,
                   opponent: tuple[bool, bool] = (True, True)) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pairs of uint8 images the flow runs on for two views ``a``, ``b`` ([H, W] grey uint8 or
    [H, W, 3] sRGB): "luma" the grey pair; "colour" the grey pair and those of the
    :func:`opponent_channels` that ``opponent`` keeps (both views must be colour)."""
    pairs = [(to_gray8(a), to_gray8(b))]
    if channels == "colour":
        if a.ndim != 3 or b.ndim != 3:
            raise ValueError("colour corrections need colour views")
        pairs += [p for p, keep in zip(opponent_channels(to_rgb8(a), to_rgb8(b)), opponent) if keep]
    elif channels != "luma":
        raise ValueError(f"channels must be 'luma' or 'colour', got {channels!r}")
    return pairs


def patterned_opponents(vertices: np.ndarray, faces: np.ndarray, region: np.ndarray, cameras: list[Camera],
                        images: list[np.ndarray]) -> tuple[bool, bool]:
    """Which :func:`opponent_channels` show a pattern on the faces of ``faces`` whose vertices are
    all in ``region`` [V] bool (the free garment) at ``vertices``, seen in ``images`` (sRGB) from
    ``cameras``: a channel does where its local contrast (standard deviation in 7 x 7 windows of
    the channel blurred by 1 px) exceeds its pixel noise (the median distance of the channel from
    that blur), as medians over the region's pixels two pixels inside its outline. A plain
    garment's opponent channels hold only noise: their flow would pull the corrections toward no
    motion."""
    import cv2

    contrast, noise = [[], []], [[], []]
    inner = np.asarray(region, bool)[np.asarray(faces)].all(1)
    for cam, im in zip(cameras, images):
        _, face, _ = rasterize(vertices, faces, cam)
        m = (face >= 0) & inner[np.maximum(face, 0)]
        m = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        if not m.any():
            continue
        f = to_rgb8(im).astype(np.float32)
        for k, ch in enumerate((f[..., 0] - f[..., 1], 0.5 * (f[..., 0] + f[..., 1]) - f[..., 2])):
            sm = cv2.GaussianBlur(ch, (0, 0), 1.0)
            mu, sq = cv2.blur(sm, (7, 7)), cv2.blur(sm * sm, (7, 7))
            contrast[k].append(np.sqrt(np.maximum(sq - mu * mu, 0.0))[m])
            noise[k].append(np.abs(ch - sm)[m])
    return tuple(bool(c) and float(np.median(np.concatenate(c))) > float(np.median(np.concatenate(n)))
                 for c, n in zip(contrast, noise))


def garment_texture(vertices: np.ndarray, faces: np.ndarray, region: np.ndarray, cameras: list[Camera],
                    images: list[np.ndarray], blur: float = 1.0) -> float:
    """The median :func:`texture_strength` (levels per pixel) of the luma of ``images`` (sRGB)
    blurred by ``blur`` px, over the pixels of the faces of ``faces`` whose vertices are all in
    ``region`` [V] bool (the free garment) at ``vertices``, two pixels inside its outline. The blur
    takes out texture finer than a pixel (a plain fabric's weave, render noise), which is aliased
    and does not move with the cloth; a print or a plaid of several pixels stays."""
    import cv2

    vals = []
    inner = np.asarray(region, bool)[np.asarray(faces)].all(1)
    for cam, im in zip(cameras, images):
        _, face, _ = rasterize(vertices, faces, cam)
        m = (face >= 0) & inner[np.maximum(face, 0)]
        m = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        if m.any():
            g = np.asarray(to_gray8(im), np.float32)
            vals.append(texture_strength(cv2.GaussianBlur(g, (0, 0), blur) if blur > 0 else g)[m])
    return float(np.median(np.concatenate(vals))) if vals else 0.0


def scaled_flow(image0: np.ndarray, image1: np.ndarray, preset: str, factor: int) -> np.ndarray:
    """:func:`optical_flow` of two uint8 images computed at 1/``factor`` of their size (area
    average) and brought back to full-resolution pixels (bilinear, times ``factor``). At half size
    a texture aliased at two pixels averages out, and what is left (colour patches, shading,
    outlines) locks the flow on errors of several full-resolution pixels."""
    if factor <= 1:
        return optical_flow(image0, image1, preset)
    import cv2

    H, W = image0.shape[:2]
    size = (max(8, round(W / factor)), max(8, round(H / factor)))
    a = cv2.resize(image0, size, interpolation=cv2.INTER_AREA)
    b = cv2.resize(image1, size, interpolation=cv2.INTER_AREA)
    f = optical_flow(a, b, preset)
    sx, sy = W / size[0], H / size[1]
    # pixel centres: x_full = (x_small + 0.5) * s - 0.5
    up = cv2.resize(f.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR).astype(np.float64)
    up[..., 0] *= sx
    up[..., 1] *= sy
    return up


def shading_free(image: np.ndarray, sigma: float) -> np.ndarray:
    """[H, W] uint8: a uint8 channel ``image`` less its Gaussian blur of ``sigma`` px, at 128 (a
    high-pass, the "texture" part of a structure-texture decomposition: Wedel et al. 2009, "An
    improved algorithm for TV-L1 optical flow"). Shading varies slowly over the cloth and changes
    as the cloth turns against the lights; the flow of the high-passed pair follows the texture
    (and the outlines) that move with the cloth, not the shading that does not."""
    import cv2

    a = np.asarray(image, np.float32)
    return np.clip(np.rint(128.0 + a - cv2.GaussianBlur(a, (0, 0), sigma)), 0, 255).astype(np.uint8)


def texture_strength(image: np.ndarray, window: int = 5) -> np.ndarray:
    """[H, W] float64: the smaller eigenvalue's square root of the structure tensor of a uint8
    channel ``image`` [H, W] over ``window`` x ``window`` pixels (Shi and Tomasi's "good features to
    track"): the root-mean-square intensity gradient, in levels per pixel, in the direction where
    the window varies least. A flow vector is only measured where both directions vary (a plain
    patch has none, an edge or a stripe one); elsewhere it follows the shading or the smoothness
    of the flow's own search."""
    import cv2

    a = np.asarray(image, np.float32)
    gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3) / 8.0  # levels per pixel
    gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    box = (window, window)
    xx, yy, xy = (cv2.blur(p, box) for p in (gx * gx, gy * gy, gx * gy))
    half = 0.5 * (xx + yy)
    lam = half - np.sqrt(np.maximum(0.25 * (xx - yy) ** 2 + xy * xy, 0.0))
    return np.sqrt(np.maximum(lam, 0.0)).astype(np.float64)
