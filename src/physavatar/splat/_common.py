"""Constants and argument checks shared by every rasterizer backend.

Both the numba kernels and the dense PyTorch twin read these numbers, so that they render the
same image by construction (see docs/splatting.md).
"""

from __future__ import annotations


#: Tile edge in pixels (3DGS and gsplat use 16x16 tiles).
TILE = 16
#: Low-pass filter added to the projected 2D covariance, in px^2 (3DGS, gsplat's ``eps2d``):
#: every splat is at least about one pixel wide, so a Gaussian far away or seen edge-on (the
#: mesh-aligned ones are flat) still covers a pixel centre instead of aliasing away.
LOWPASS = 0.3
#: A Gaussian touches a pixel only inside its 3-sigma ellipse, d^T Sigma2d^-1 d <= 9, i.e. when
#: the exponent 0.5 d^T Sigma2d^-1 d is at most 4.5. Tiles only speed up finding those pixels.
CUTOFF_POWER = 4.5
#: Per-splat alpha below this is skipped (3DGS: 1/255, invisible in an 8-bit image).
ALPHA_MIN = 1.0 / 255.0
#: Per-splat alpha is clamped to this (3DGS), so 1 - alpha never vanishes and the backward pass
#: can recover transmittance by division.
ALPHA_MAX = 0.99
#: Compositing stops before a splat would drive transmittance below this (3DGS).
T_MIN = 1e-4
#: Off-screen Gaussians use a Jacobian evaluated at most this fraction of the half field of view
#: outside the image (3DGS / gsplat), which keeps huge off-screen splats bounded.
FOV_MARGIN = 0.3


def check_inputs(means, quats, scales, opacities, colors, viewmat, K, background):
    """Validate shapes; returns (N, D)."""
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    n = means.shape[0]
    for name, t, shape in (
        ("quats", quats, (n, 4)),
        ("scales", scales, (n, 3)),
        ("opacities", opacities, (n,)),
        ("viewmat", viewmat, (4, 4)),
        ("K", K, (3, 3)),
    ):
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must be {list(shape)}, got {list(t.shape)}")
    if colors.ndim != 2 or colors.shape[0] != n:
        raise ValueError(f"colors must be [N, D] with N={n}, got {list(colors.shape)}")
    d = colors.shape[1]
    if background is not None and tuple(background.shape) != (d,):
        raise ValueError(f"background must be [{d}], got {list(background.shape)}")
    return n, d


def fov_limits(K, width: int, height: int) -> tuple[float, float, float, float]:
    """Bounds on x/z and y/z at which the EWA Jacobian is evaluated (3DGS's frustum clamp).

    K: [3, 3] intrinsics (tensor or array).

    Returns (neg_x, pos_x, neg_y, pos_y): tx/tz is clamped to [-neg_x, pos_x], ty/tz to
    [-neg_y, pos_y]. With pixel centres at integers the image spans [-0.5, width - 0.5].
    """
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    mx = FOV_MARGIN * 0.5 * width / fx
    my = FOV_MARGIN * 0.5 * height / fy
    return (cx + 0.5) / fx + mx, (width - 0.5 - cx) / fx + mx, (cy + 0.5) / fy + my, (height - 0.5 - cy) / fy + my
