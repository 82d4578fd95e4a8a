"""Adapter to ``gsplat.rasterization`` (CUDA), imported only when it is used.

Written from gsplat's documented API (``gsplat/rendering.py``, v1.x). gsplat needs CUDA, so the
CPU machines this project is tested on skip ``tests/test_splat_gsplat.py``, which checks it
against the CPU kernels on a CUDA machine. Known differences from the CPU kernels: gsplat clamps
per-splat alpha at 0.999 (here 0.99) and draws a splat wherever its alpha reaches 1/255 inside a
3-sigma box rather than only inside its 3-sigma ellipse, so images agree only up to those edge
effects. gsplat's kernels are float32: inputs of another dtype are cast, outputs cast back.
"""

from __future__ import annotations

import torch

from ._common import LOWPASS, TILE


def available() -> bool:
    """True when CUDA is present and gsplat imports."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # a broken CUDA extension raises more than ImportError
        return False
    return True


def rasterize_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, near, far,
                     antialiased: bool = False):
    """Render C cameras at once with gsplat.

    Args:
        means [N, 3], quats [N, 4] (wxyz), scales [N, 3], opacities [N], colors [N, D];
        viewmats [C, 4, 4] world-to-camera; Ks [C, 3, 3] with pixel centres at integers (this
        project's convention); backgrounds [C, D] or None. antialiased: gsplat's
        ``rasterize_mode="antialiased"`` (opacity compensated for the low-pass).
    Returns:
        rgb [C, H, W, D], alpha [C, H, W], depth [C, H, W] (accumulated sum w_i z_i), meta dict;
        all on the CUDA device, in the dtype of ``means``.
    """
    from gsplat import rasterization

    dev = torch.device("cuda")
    dtype = means.dtype

    def cuda32(t):
        return t.to(dev, torch.float32)

    # gsplat samples pixel (i, j) at (j + 0.5, i + 0.5) in K's coordinates, this project at (j, i):
    # shifting the principal point by half a pixel makes both sample the same rays.
    Ks_g = cuda32(Ks).clone()
    Ks_g[:, 0, 2] += 0.5
    Ks_g[:, 1, 2] += 0.5
    render, alphas, meta = rasterization(
        cuda32(means), cuda32(quats), cuda32(scales), cuda32(opacities), cuda32(colors),
        cuda32(viewmats), Ks_g, int(width), int(height),
        near_plane=float(near), far_plane=float(far), eps2d=LOWPASS, tile_size=TILE,
        backgrounds=None if backgrounds is None else cuda32(backgrounds),
        render_mode="RGB+D",  # last channel: accumulated depth sum_i w_i z_i, like the CPU kernels
        packed=False, rasterize_mode="antialiased" if antialiased else "classic",
    )
    return render[..., :-1].to(dtype), alphas[..., 0].to(dtype), render[..., -1].to(dtype), meta
