"""OpenCV cameras (``physavatar.camera.Camera``) as Mitsuba perspective sensors.

The mapping, checked ray by ray against ``Camera.pixel_rays`` in tests/test_render.py:

* Axes. OpenCV camera space is x right, y down, z forward; Mitsuba's sensor space is x left,
  y up, z forward. Both are right-handed and share z, so ``to_world = c2w @ diag(-1, -1, 1, 1)``.
* Field of view. Mitsuba has one focal length; ``fov`` is the vertical angle
  ``2 atan(H / (2 fy))`` with ``fov_axis = "y"`` (Mitsuba derives the horizontal one from the
  film's aspect ratio, which is right only for square pixels, fx = fy).
* Principal point. Mitsuba puts film pixel ``i`` on ``[i, i + 1]`` (centre ``i + 0.5``) while
  OpenCV puts its centre at ``i``, so the OpenCV principal point ``cx`` sits at ``cx + 0.5`` in
  film coordinates. Mitsuba's ``principal_point_offset_x`` is that point's offset from the film
  centre as a fraction of the width, measured along the sensor's own x axis, which points left:
  ``ppo_x = (W / 2 - (cx + 0.5)) / W``, and likewise ``ppo_y = (H / 2 - (cy + 0.5)) / H``.
* Film. ``hdrfilm`` of W x H with RGBA output (alpha = coverage) and the ``box`` reconstruction
  filter, so each sample lands in exactly the pixel it was drawn in: silhouettes are not blurred
  across neighbours, and a pixel's alpha is the fraction of its area that the meshes cover.
"""

from __future__ import annotations

import numpy as np

from physavatar.camera import Camera

from .backend import mitsuba

# Mitsuba's perspective sensor has a single focal length. A camera whose fx and fy differ moves a
# border pixel by |fx - fy| / fx * (distance from the principal point) pixels when rendered with
# fy alone; below this many pixels the difference is invisible next to sampling noise.
MAX_ANISOTROPY_PX = 0.05

OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])


def check_pinhole(camera: Camera) -> None:
    """Raise ValueError if ``camera`` has skew or non-square pixels Mitsuba cannot represent."""
    K = camera.K
    fx, fy, s = K[0, 0], K[1, 1], K[0, 1]
    if not (fx > 0 and fy > 0):
        raise ValueError(f"camera {camera.name!r}: focal lengths must be positive, got fx={fx}, fy={fy}")
    if np.any(K[2] != [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise ValueError(f"camera {camera.name!r}: K's last row must be [0, 0, 1] and K[1, 0] = 0")
    reach = max(K[0, 2] + 0.5, camera.width - 0.5 - K[0, 2])
    if abs(fx - fy) / fx * reach > MAX_ANISOTROPY_PX or abs(s) / fy * camera.height > MAX_ANISOTROPY_PX:
        raise ValueError(
            f"camera {camera.name!r}: fx={fx:.4f}, fy={fy:.4f}, skew={s:.4f}; Mitsuba's perspective "
            f"sensor needs square pixels without skew (off by more than {MAX_ANISOTROPY_PX} px here)"
        )


def camera_to_world_mitsuba(camera: Camera) -> np.ndarray:
    """[4, 4] Mitsuba sensor ``to_world`` (camera-to-world with x and y flipped)."""
    return camera.c2w @ OPENCV_TO_MITSUBA


def principal_point_offset(camera: Camera) -> tuple[float, float]:
    """Mitsuba's ``(principal_point_offset_x, principal_point_offset_y)`` for ``camera``."""
    W, H = camera.width, camera.height
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    return (0.5 * W - (cx + 0.5)) / W, (0.5 * H - (cy + 0.5)) / H


def sensor_dict(
    camera: Camera,
    spp: int = 16,
    *,
    near_clip: float = 1e-3,
    far_clip: float = 1e4,
    sampler: str = "independent",
) -> dict:
    """Mitsuba dict of a ``perspective`` sensor that reproduces ``camera`` pixel for pixel."""
    check_pinhole(camera)
    mi = mitsuba()
    ppx, ppy = principal_point_offset(camera)
    return {
        "type": "perspective",
        "to_world": mi.ScalarTransform4f(camera_to_world_mitsuba(camera).tolist()),
        "fov": float(np.degrees(2.0 * np.arctan(0.5 * camera.height / camera.K[1, 1]))),
        "fov_axis": "y",
        "principal_point_offset_x": float(ppx),
        "principal_point_offset_y": float(ppy),
        "near_clip": float(near_clip),
        "far_clip": float(far_clip),
        "sampler": {"type": sampler, "sample_count": int(spp)},
        "film": {
            "type": "hdrfilm",
            "width": int(camera.width),
            "height": int(camera.height),
            "pixel_format": "rgba",
            "component_format": "float32",
            "rfilter": {"type": "box"},
        },
    }


def make_sensor(camera: Camera, spp: int = 16, **kwargs):
    """A loaded Mitsuba sensor for ``camera`` (see :func:`sensor_dict`)."""
    return mitsuba().load_dict(sensor_dict(camera, spp, **kwargs))
