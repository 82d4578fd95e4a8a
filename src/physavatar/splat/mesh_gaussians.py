"""Mesh-aligned Gaussians (PhysAvatar Sec. 3.1): one flat Gaussian per face, attached to the mesh.

Each face carries a Gaussian at its barycentre whose rotation is the face's local frame: x along
one edge (the longest edge of the first frame, kept fixed per face afterwards so the frame does not
jump when edge lengths cross), z along the face normal, y = z x x. The two in-plane scales are
free parameters (log space); the normal-direction scale is a small constant so the Gaussian lies
on the surface. Everything is a torch function of the vertices, so photometric gradients reach the
tracked mesh.
"""

from __future__ import annotations

import torch

#: Normal-direction standard deviation (metres): thin enough to lie on the surface, thick enough
#: that the 3D covariance stays well conditioned in float32.
NORMAL_SCALE = 1e-4


def longest_edge_index(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """[F] index k in {0, 1, 2} of each face's longest edge, edge k running faces[:, k] -> faces[:, (k+1) % 3].

    Args:
        vertices: [V, 3]. faces: [F, 3] vertex indices.
    """
    tri = vertices.detach()[faces]  # [F, 3, 3]
    edges = tri.roll(-1, dims=1) - tri  # edge k = v_{k+1} - v_k
    return edges.norm(dim=-1).argmax(dim=1)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation matrices -> [..., 4] unit quaternions (w, x, y, z) with w >= 0.

    Shepperd's method: of the four algebraically equal formulas, use the one whose square root has
    the largest argument, so no branch divides by a near-zero number. Differentiable.
    """
    m = R.reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    args = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    # The clamp only matters in branches that are not selected; it keeps their values (and thus
    # their zero-weighted gradients) finite.
    r = 0.5 * torch.sqrt(args.clamp(min=1e-12))  # [M, 4]
    d = 4 * r
    cand = torch.stack(
        [
            torch.stack([r[:, 0], (m21 - m12) / d[:, 0], (m02 - m20) / d[:, 0], (m10 - m01) / d[:, 0]], -1),
            torch.stack([(m21 - m12) / d[:, 1], r[:, 1], (m01 + m10) / d[:, 1], (m02 + m20) / d[:, 1]], -1),
            torch.stack([(m02 - m20) / d[:, 2], (m01 + m10) / d[:, 2], r[:, 2], (m12 + m21) / d[:, 2]], -1),
            torch.stack([(m10 - m01) / d[:, 3], (m02 + m20) / d[:, 3], (m12 + m21) / d[:, 3], r[:, 3]], -1),
        ],
        1,
    )  # [M, 4 branches, 4]
    best = args.argmax(dim=-1)
    q = cand[torch.arange(m.shape[0]), best]
    q = torch.where(q[:, :1] < 0, -q, q)  # q and -q are one rotation; pick w >= 0
    q = q / q.norm(dim=-1, keepdim=True)
    return q.reshape(R.shape[:-2] + (4,))


def face_frames(vertices: torch.Tensor, faces: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
    """[F, 3, 3] rotation matrices whose columns are the face frame (x along the chosen edge, y, z = normal).

    Args:
        vertices: [V, 3]. faces: [F, 3]. edge_index: [F] from :func:`longest_edge_index`.
    """
    tri = vertices[faces]  # [F, 3, 3]
    ar = torch.arange(faces.shape[0], device=faces.device)
    ex = tri[ar, (edge_index + 1) % 3] - tri[ar, edge_index]
    ex = ex / ex.norm(dim=-1, keepdim=True)
    ez = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ez = ez / ez.norm(dim=-1, keepdim=True)
    ey = torch.linalg.cross(ez, ex)  # unit: ex lies in the face plane, so ex is orthogonal to ez
    return torch.stack([ex, ey, ez], dim=-1)


def mesh_to_gaussians(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    log_scales: torch.Tensor,
    edge_index: torch.Tensor | None = None,
    normal_scale: float = NORMAL_SCALE,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gaussians attached to a triangle mesh, differentiable w.r.t. the vertices and log-scales.

    Args:
        vertices: [V, 3] (metres), e.g. one tracked frame.
        faces: [F, 3] vertex indices (long).
        log_scales: [F, 2] natural log of the in-plane standard deviations along the face's x
            and y axes.
        edge_index: [F] which edge defines each face's x axis; compute it once on the first frame
            with :func:`longest_edge_index` and pass it for every later frame. None computes it
            from these vertices.
        normal_scale: standard deviation along the face normal (metres).
    Returns:
        means: [F, 3] face barycentres; quats: [F, 4] (w, x, y, z) of the face frames;
        scales: [F, 3] = (exp(log_scales), normal_scale).
    """
    faces = faces.long()
    if edge_index is None:
        edge_index = longest_edge_index(vertices, faces)
    means = vertices[faces].mean(dim=1)
    quats = rotmat_to_quat(face_frames(vertices, faces, edge_index.long()))
    scales = torch.cat([log_scales.exp(), torch.full_like(log_scales[:, :1], normal_scale)], dim=-1)
    return means, quats, scales
