"""The images the fit compares against: every training camera's image and mask at each pyramid
level, the first frame's colours read from them, and grey views for the optical flow."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from ...camera import Camera
from ...capture import Capture
from ...render.image import srgb_to_linear
from .flow import to_gray8, to_rgb8


@dataclass
class View:
    """One camera at one pyramid level: camera, image [H, W, 3] sRGB, mask [H, W]."""

    camera: Camera
    image: torch.Tensor
    mask: torch.Tensor


def _resize(a: np.ndarray, w: int, h: int) -> np.ndarray:
    if a.shape[1] == w and a.shape[0] == h:
        return a
    # box filter = the area average of each coarse pixel, the image a coarse camera would see
    if a.ndim == 2:
        return np.asarray(Image.fromarray(a.astype(np.float32), mode="F").resize((w, h), Image.BOX))
    return np.stack([_resize(a[..., c], w, h) for c in range(a.shape[2])], -1)


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return a
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(a, (sigma, sigma) + (0,) * (a.ndim - 2), mode="nearest")


def load_views(capture: Capture, frame: int, cameras: list[Camera], factor: float, blur: float = 0.0,
               images: list[np.ndarray] | None = None) -> list[View]:
    """Every camera's image and mask box-filtered to ``factor`` of the capture's size, then
    blurred with a Gaussian of ``blur`` px (``FitConfig.target_blur``). ``images``: the
    cameras' full-resolution images of ``frame`` when already read."""
    out = []
    for k, cam in enumerate(cameras):
        c = cam.scaled(factor) if factor != 1.0 else cam
        full = capture.image(cam.name, frame) if images is None else images[k]
        img = _blur(_resize(full, c.width, c.height), blur)
        msk = _blur(_resize(capture.mask(cam.name, frame), c.width, c.height), blur)
        out.append(View(c, torch.from_numpy(np.array(img, np.float32)),
                        torch.from_numpy(np.array(msk, np.float32))))
    return out


def initial_colors(vertices: np.ndarray, faces: np.ndarray, views: list[View]) -> np.ndarray:
    """[F, 3] linear RGB: per face, the median over cameras of the pixel under its barycentre
    (inside the mask). Occlusion is ignored — the fit corrects the few wrong faces; this only
    saves the colours most of their way from grey."""
    bary = vertices[faces].mean(1)
    samples = []
    for v in views:
        uv, z = v.camera.project(bary)
        u = np.rint(uv[:, 0]).astype(int)
        w = np.rint(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < v.camera.width) & (w >= 0) & (w < v.camera.height)
        s = np.full((len(faces), 3), np.nan)
        m = v.mask.numpy()
        ok[ok] &= m[w[ok], u[ok]] > 0.5
        s[ok] = v.image.numpy()[w[ok], u[ok]]
        samples.append(s)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(np.stack(samples), axis=0)
    med = np.where(np.isfinite(med), med, 0.5)
    return srgb_to_linear(med).astype(np.float32)


def grey_views(capture: Capture, frame: int, cameras: list[Camera]) -> list[np.ndarray]:
    """The cameras' full-resolution images of ``frame`` as grey uint8 (:func:`~.flow.to_gray8`)."""
    return [to_gray8(capture.image(c.name, frame)) for c in cameras]


def flow_views(capture: Capture, frame: int, cameras: list[Camera], channels: str = "luma") -> list[np.ndarray]:
    """The views the flow start keeps: :func:`grey_views`, or sRGB uint8 [H, W, 3] for
    ``channels="colour"``."""
    if channels != "colour":
        return grey_views(capture, frame, cameras)
    return [to_rgb8(capture.image(c.name, frame)) for c in cameras]

