"""Dense PyTorch twin of the CPU rasterizer: slow, short, and differentiable by autograd.

PyTorch implementation of :func:`physavatar.splat.rasterize` (``backend="torch"``). Every
Gaussian is evaluated at every pixel centre and composited with ``cumprod``; nothing is tiled,
nothing is written by hand in the backward direction. It is the reference that the numba kernels
are tested against, and it is only practical for small scenes (memory grows as H * W * N).
"""

from __future__ import annotations

import torch

from ._common import ALPHA_MAX, ALPHA_MIN, CUTOFF_POWER, LOWPASS, T_MIN, fov_limits

#: Largest H * W * N the twin accepts: each [H * W, N] intermediate is 8 bytes per entry in float64
#: and autograd keeps about a dozen of them.
MAX_DENSE = 2e7


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] quaternions (w, x, y, z; any norm) -> [N, 3, 3] rotation matrices."""
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def _ewa_jacobian(tx, ty, tz, K, width, height):
    """[N, 2, 3] Jacobian of the perspective projection at camera points (tx, ty, tz > 0), with
    x/z and y/z clamped to the field of view's guard band (as 3DGS / gsplat)."""
    fx, fy = K[0, 0], K[1, 1]
    nx, px, ny, py = fov_limits(K, width, height)
    xc = tz * torch.clamp(tx / tz, -nx, px)
    yc = tz * torch.clamp(ty / tz, -ny, py)
    zero = torch.zeros_like(tz)
    return torch.stack(
        [fx / tz, zero, -fx * xc / tz**2, zero, fy / tz, -fy * yc / tz**2], dim=-1
    ).reshape(-1, 2, 3)


def projected_covariance(means, quats, scales, viewmat, K, width, height):
    """[N, 2, 2] EWA covariance J W R S S^T R^T W^T J^T of each Gaussian in pixels², without the
    low-pass; also [N] camera z. Differentiable w.r.t. means, quats and scales."""
    Rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    t = means @ Rw.T + tw
    tx, ty, tz = t.unbind(-1)
    tzs = torch.where(tz > 0, tz, torch.ones_like(tz))  # culled later; keeps autograd finite
    J = _ewa_jacobian(tx, ty, tzs, K, width, height)
    A = J @ Rw @ (quat_to_rotmat(quats) * scales[:, None, :])  # J W R S
    return A @ A.transpose(1, 2), tz


def antialias_compensation(means, quats, scales, viewmat, K, width, height):
    """[N] sqrt(det Σ / det(Σ + LOWPASS I)): the opacity factor that makes the low-pass conserve
    each splat's mass (gsplat's ``rasterize_mode="antialiased"``, Mip-Splatting's 2D filter).

    The plain low-pass widens every splat to about a pixel at full opacity, so a surface of
    sub-pixel splats renders a silhouette wider than the surface (measured on the demo dress at
    128²: +20 % alpha over the true mask; compensated, +3 %). Scaling the opacity by the ratio of
    the Gaussian's peak heights keeps its integral, so the image is the surface blurred by the
    low-pass, with edges where they belong.
    """
    cov, _ = projected_covariance(means, quats, scales, viewmat, K, width, height)
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = (a * c - b * b).clamp(min=0.0)
    det_lp = (a + LOWPASS) * (c + LOWPASS) - b * b
    return torch.sqrt(det / det_lp + 1e-20)


def project(means, quats, scales, viewmat, K, width, height, near, far):
    """EWA projection of 3D Gaussians (Zwicker et al. 2001, as in 3DGS).

    Args:
        means: [N, 3] world centres. quats: [N, 4] wxyz. scales: [N, 3] standard deviations (m).
        viewmat: [4, 4] world-to-camera. K: [3, 3] pixels.
    Returns:
        means2d: [N, 2] pixel coordinates (centres at integers); depths: [N] camera z;
        conics: [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]];
        valid: [N] bool, the centre lies within [near, far].
    """
    Rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    t = means @ Rw.T + tw
    tx, ty, tz = t.unbind(-1)
    valid = (tz >= near) & (tz <= far)
    # Culled Gaussians get a harmless depth so no inf/nan reaches autograd through torch.where.
    tz = torch.where(valid, tz, torch.ones_like(tz))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    J = _ewa_jacobian(tx, ty, tz, K, width, height)
    M = quat_to_rotmat(quats) * scales[:, None, :]  # R S
    A = J @ Rw @ M  # [N, 2, 3]; Sigma2d = A A^T = J W R S S^T R^T W^T J^T
    cov = A @ A.transpose(1, 2) + LOWPASS * torch.eye(2, dtype=means.dtype)
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    means2d = torch.stack([fx * tx / tz + cx, fy * ty / tz + cy], dim=-1)
    return means2d, tz, conics, valid


def rasterize_dense(means, quats, scales, opacities, colors, viewmat, K, width, height, background, near, far):
    """Render [H, W, D] colour, [H, W] alpha and [H, W] accumulated depth densely.

    Same semantics as the numba kernels: a splat contributes to a pixel when its centre is in
    [near, far], the pixel centre lies in its 3-sigma ellipse, and alpha = min(0.99, o * G) is at
    least 1/255; splats are composited front to back in order of camera z (stable by index), and
    compositing stops before the splat that would bring transmittance below 1e-4.
    """
    if height * width * means.shape[0] > MAX_DENSE:
        raise ValueError(
            f"the dense twin would evaluate {height * width * means.shape[0]:.2e} pixel-Gaussian pairs "
            f"(limit {MAX_DENSE:.0e}); use backend='numba' for scenes this large"
        )
    means2d, depths, conics, valid = project(means, quats, scales, viewmat, K, width, height, near, far)
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means.dtype), torch.arange(width, dtype=means.dtype), indexing="ij"
    )
    dx = means2d[None, :, 0] - xs.reshape(-1, 1)  # [P, N], P = H * W
    dy = means2d[None, :, 1] - ys.reshape(-1, 1)
    a, b, c = conics.unbind(-1)
    power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(opacities * torch.exp(-power), max=ALPHA_MAX)
    hit = valid & (power <= CUTOFF_POWER) & (alpha >= ALPHA_MIN)
    alpha = torch.where(hit, alpha, torch.zeros_like(alpha))

    order = torch.sort(torch.where(valid, depths, torch.full_like(depths, float("inf"))).detach(), stable=True).indices
    alpha = alpha[:, order]
    # T after each splat if none were cut; it only decreases, so the splats kept are a prefix.
    keep = torch.cumprod(1 - alpha, dim=1) >= T_MIN
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    one_minus = 1 - alpha
    T_before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), one_minus[:, :-1]], dim=1), dim=1)
    w = alpha * T_before  # [P, N] compositing weights
    T_final = T_before[:, -1] * one_minus[:, -1] if alpha.shape[1] else torch.ones(alpha.shape[0], dtype=means.dtype)
    rgb = w @ colors[order]
    if background is not None:
        rgb = rgb + T_final[:, None] * background
    depth = w @ depths[order]
    return (
        rgb.reshape(height, width, -1),
        (1 - T_final).reshape(height, width),
        depth.reshape(height, width),
        dict(means2d=means2d.detach(), depths=depths.detach(), conics=conics.detach(), valid=valid),
    )
