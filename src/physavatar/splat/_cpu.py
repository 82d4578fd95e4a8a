"""torch.autograd.Function around the numba kernels (``backend="numba"``)."""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch.autograd.function import once_differentiable

from . import _kernels as kn
from ._common import fov_limits


# Tiles differ a lot in work (the silhouette versus empty sky): hand them to threads in small
# chunks instead of numba's default equal static split.
_TILE_CHUNK = 4


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)


class RasterizeCPU(torch.autograd.Function):
    """Forward: projection, binning and compositing kernels. Backward: the hand-written kernels.

    Gradients flow to means, quats, scales, opacities, colors and background; the camera
    (viewmat, K) is treated as constant.
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, background, viewmat, K, width, height, near, far, meta):
        n, d = means.shape[0], colors.shape[1]
        Kn = _np(K)
        intr = np.array([Kn[0, 0], Kn[1, 1], Kn[0, 2], Kn[1, 2]])
        lims = np.array(fov_limits(Kn, width, height))
        m, q, s, vm = _np(means), _np(quats), _np(scales), _np(viewmat)
        op, col = _np(opacities), _np(colors)
        bg = _np(background) if background is not None else np.zeros(d)

        means2d = np.empty((n, 2))
        depths = np.empty(n)
        conics = np.empty((n, 3))
        rects = np.empty((n, 4), dtype=np.int64)
        kn.project_forward(m, q, s, vm, intr, lims, width, height, near, far, means2d, depths, conics, rects)
        # Culled Gaussians sort last; they are in no tile anyway.
        sort_key = np.where(rects[:, 0] <= rects[:, 1], depths, np.inf)
        offsets, ids = kn.bin_tiles(rects, sort_key, width, height)
        rgb = np.empty((height, width, d))
        depth = np.empty((height, width))
        T = np.empty((height, width))
        count = np.empty((height, width), dtype=np.int32)
        with numba.parallel_chunksize(_TILE_CHUNK):
            kn.raster_forward(offsets, ids, rects, means2d, conics, op, col, depths, bg, width, height, rgb, depth, T, count)

        ctx.arrays = dict(m=m, q=q, s=s, vm=vm, intr=intr, lims=lims, op=op, col=col, bg=bg,
                          means2d=means2d, depths=depths, conics=conics, rects=rects,
                          offsets=offsets, ids=ids, T=T, count=count)
        ctx.sizes = (width, height, near, far, background is not None)
        ctx.dtype = means.dtype
        ctx.device = means.device
        meta.update(means2d=torch.from_numpy(means2d), depths=torch.from_numpy(depths),
                    conics=torch.from_numpy(conics), visible=torch.from_numpy(rects[:, 0] <= rects[:, 1]),
                    n_intersections=int(ids.shape[0]))
        dt = means.dtype
        return (torch.from_numpy(rgb).to(dt), torch.from_numpy(1.0 - T).to(dt), torch.from_numpy(depth).to(dt))

    @staticmethod
    @once_differentiable
    def backward(ctx, g_rgb, g_alpha, g_depth):
        a = ctx.arrays
        width, height, near, far, has_bg = ctx.sizes
        n, d = a["m"].shape[0], a["col"].shape[1]
        g_isect = np.empty((a["ids"].shape[0], kn.G_COL + d))
        with numba.parallel_chunksize(_TILE_CHUNK):
            kn.raster_backward(a["offsets"], a["ids"], a["rects"], a["means2d"], a["conics"], a["op"], a["col"],
                               a["depths"], a["bg"], width, height, a["T"], a["count"],
                               _np(g_rgb), _np(g_alpha), _np(g_depth), g_isect)
        g = kn.reduce_isect(a["ids"], g_isect, n)
        g_means, g_quats, g_scales = np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3))
        kn.project_backward(a["m"], a["q"], a["s"], a["vm"], a["intr"], a["lims"], near, far, a["conics"],
                            a["rects"], g, g_means, g_quats, g_scales)
        dt = ctx.dtype
        t = lambda x: torch.from_numpy(np.ascontiguousarray(x)).to(device=ctx.device, dtype=dt)  # noqa: E731
        g_bg = t((_np(g_rgb) * a["T"][..., None]).sum(axis=(0, 1))) if has_bg else None
        return (t(g_means), t(g_quats), t(g_scales), t(g[:, kn.G_OPA]), t(g[:, kn.G_COL:]), g_bg,
                None, None, None, None, None, None, None)
