"""Differentiable 3D Gaussian splatting: one entry point, three backends.

``rasterize`` renders N anisotropic 3D Gaussians into one pinhole camera (OpenCV convention,
pixel centres at integer coordinates, like :class:`physavatar.camera.Camera`) and is
differentiable with respect to every Gaussian parameter. Backends:

- ``"numba"``: tile-based CPU kernels with a hand-written backward pass (``_kernels.py``).
- ``"torch"``: the dense PyTorch twin (``_torch_impl.py``); every Gaussian at every pixel,
  gradients by autograd. Slow; the reference the kernels are tested against.
- ``"gsplat"``: ``gsplat.rasterization`` on CUDA (``_gsplat.py``).
- ``"auto"``: gsplat when CUDA is available and gsplat imports, else numba.

The image model is that of 3DGS (Kerbl et al. 2023); docs/splatting.md lists the conventions.
"""

from __future__ import annotations

import torch

from . import _gsplat
from ._common import check_inputs
from ._torch_impl import antialias_compensation, rasterize_dense

BACKENDS = ("auto", "numba", "torch", "gsplat")


def resolve_backend(backend: str) -> str:
    """The backend ``backend`` renders with here: "auto" becomes "gsplat" or "numba"."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        return "gsplat" if _gsplat.available() else "numba"
    return backend


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    near: float = 0.01,
    far: float = 100.0,
    backend: str = "auto",
    antialiased: bool = False,
) -> dict:
    """Render 3D Gaussians into one camera.

    Args:
        means: [N, 3] centres in world coordinates (metres).
        quats: [N, 4] rotations as quaternions (w, x, y, z); need not be normalised.
        scales: [N, 3] standard deviations along the rotated axes (metres, not log).
        opacities: [N] in [0, 1].
        colors: [N, D] per-Gaussian colour or feature (D = 3 for RGB; any D works).
        viewmat: [4, 4] world-to-camera (OpenCV: x right, y down, z forward).
        K: [3, 3] intrinsics in pixels, pixel centres at integer coordinates.
        width, height: image size in pixels.
        background: [D] colour behind the Gaussians; None means zeros.
        near, far: Gaussians whose centre has camera z outside [near, far] are dropped whole.
        backend: "auto", "numba", "torch" or "gsplat" (see the module docstring).
        antialiased: scale each opacity by sqrt(det Σ2d / det(Σ2d + LOWPASS I)) so the low-pass
            keeps every splat's mass (gsplat's ``rasterize_mode="antialiased"``;
            :func:`antialias_compensation`, differentiable through torch on every backend).

    Returns:
        dict with
        rgb: [H, W, D] composited colour (background included);
        alpha: [H, W] accumulated opacity 1 - T_final;
        depth: [H, W] alpha-weighted camera z, sum_i w_i z_i (divide by alpha for the expected
            depth of a covered pixel; ``expected_depth`` does that);
        meta: dict with backend (str) and, for numba/torch, means2d [N, 2], depths [N],
            conics [N, 3] (upper triangle of the inverse 2D covariance; not differentiable).
    All outputs are differentiable w.r.t. means, quats, scales, opacities, colors and background
    (not w.r.t. viewmat and K on the numba backend).
    """
    check_inputs(means, quats, scales, opacities, colors, viewmat, K, background)
    which = resolve_backend(backend)
    if which == "gsplat":
        rgb, alpha, depth, meta = _gsplat.rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmat[None], K[None], width, height,
            None if background is None else background[None], near, far, antialiased,
        )
        dev = means.device
        return dict(rgb=rgb[0].to(dev), alpha=alpha[0].to(dev), depth=depth[0].to(dev),
                    meta=dict(meta, backend="gsplat"))
    if antialiased:
        opacities = opacities * antialias_compensation(means, quats, scales, viewmat, K, width, height)
    if which == "torch":
        rgb, alpha, depth, meta = rasterize_dense(
            means, quats, scales, opacities, colors, viewmat, K, int(width), int(height), background, near, far
        )
        return dict(rgb=rgb, alpha=alpha, depth=depth, meta=dict(meta, backend="torch"))
    from ._cpu import RasterizeCPU  # numba compiles (or loads its cache) on first use

    meta: dict = {}
    rgb, alpha, depth = RasterizeCPU.apply(
        means, quats, scales, opacities, colors, background, viewmat, K, int(width), int(height),
        float(near), float(far), meta,
    )
    dev = means.device
    return dict(rgb=rgb.to(dev), alpha=alpha.to(dev), depth=depth.to(dev), meta=dict(meta, backend="numba"))


def rasterize_batch(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    backgrounds: torch.Tensor | None = None,
    near: float = 0.01,
    far: float = 100.0,
    backend: str = "auto",
    antialiased: bool = False,
) -> dict:
    """Render the same Gaussians into C cameras of one size.

    Args:
        means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colors [N, D]: as in
        :func:`rasterize`. viewmats: [C, 4, 4]. Ks: [C, 3, 3]. backgrounds: [C, D] or None.
        antialiased: as in :func:`rasterize`.
    Returns:
        dict with rgb [C, H, W, D], alpha [C, H, W], depth [C, H, W], meta (list of C dicts, or
        gsplat's one dict).
    """
    which = resolve_backend(backend)
    if which == "gsplat":
        for c in range(viewmats.shape[0]):
            check_inputs(means, quats, scales, opacities, colors, viewmats[c], Ks[c],
                         None if backgrounds is None else backgrounds[c])
        rgb, alpha, depth, meta = _gsplat.rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, near, far, antialiased
        )
        dev = means.device
        return dict(rgb=rgb.to(dev), alpha=alpha.to(dev), depth=depth.to(dev), meta=dict(meta, backend="gsplat"))
    outs = [
        rasterize(means, quats, scales, opacities, colors, viewmats[c], Ks[c], width, height,
                  None if backgrounds is None else backgrounds[c], near, far, which, antialiased)
        for c in range(viewmats.shape[0])
    ]
    return dict(
        rgb=torch.stack([o["rgb"] for o in outs]),
        alpha=torch.stack([o["alpha"] for o in outs]),
        depth=torch.stack([o["depth"] for o in outs]),
        meta=[o["meta"] for o in outs],
    )


def expected_depth(out: dict, eps: float = 1e-10) -> torch.Tensor:
    """[..., H, W] expected camera z of the visible surface: depth / alpha (gsplat's "ED")."""
    return out["depth"] / out["alpha"].clamp(min=eps)
