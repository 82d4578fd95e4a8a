"""Differentiable losses of the tracking stage (PhysAvatar Sec. 3.1, Eqs. 1-3), in torch.

- :func:`ssim` — SSIM with the reference setting of :func:`physavatar.metrics.ssim` (11x11
  Gaussian window, sigma 1.5, K1 0.01, K2 0.03, population variances, "valid" region), batched
  and differentiable.
- :class:`IsometryLoss` — Eq. 2: edge lengths of the 1-ring against the first frame, averaged per
  vertex over its ring, then over vertices.
- :class:`NormalLoss` — Eq. 3: 1 - n(f) . n(f') over pairs of faces sharing an edge.
- :class:`CollisionLoss`, :class:`AnchorLoss` — the garment kept outside the body, the body and
  the garment boundary held near their skinned pose.
- :func:`linear_to_srgb` — the sRGB transfer curve (IEC 61966-2-1), so splats can be composited in
  linear light like the renderer that made the capture, then compared to the sRGB images.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ...geometry import mesh_edges


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(pred: torch.Tensor, gt: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Mean structural similarity of image batches, differentiable.

    Args:
        pred, gt: [B, H, W, C] (or [H, W, C]) in [0, data_range], H and W at least 11.
    Returns:
        scalar: the SSIM map over the "valid" region (where the window fits inside the image),
        averaged over pixels, channels and the batch. For one image this equals
        ``physavatar.metrics.ssim`` (the MATLAB ``ssim_index`` / skimage Gaussian setting).
    """
    if pred.ndim == 3:
        pred, gt = pred[None], gt[None]
    B, H, W, C = pred.shape
    if min(H, W) < 11:
        raise ValueError(f"SSIM needs images of at least 11 px a side, got {H}x{W}")
    win = _gaussian_window().to(pred.dtype)
    # separable depthwise convolution: one [1, 1, 11] and one [1, 11, 1] kernel per channel
    kx = win.view(1, 1, 1, -1).repeat(C, 1, 1, 1)
    ky = win.view(1, 1, -1, 1).repeat(C, 1, 1, 1)

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(x, kx, groups=C), ky, groups=C)

    x = pred.permute(0, 3, 1, 2)
    y = gt.permute(0, 3, 1, 2)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    # one conv pass over all five statistics' inputs (stacked on the batch axis)
    stats = blur(torch.cat([x, y, x * x, y * y, x * y], 0))
    mx, my, xx, yy, xy = stats.split(B, 0)
    sxx = xx - mx * mx
    syy = yy - my * my
    sxy = xy - mx * my
    num = (2 * mx * my + c1) * (2 * sxy + c2)
    den = (mx * mx + my * my + c1) * (sxx + syy + c2)
    return (num / den).mean()


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Linear values -> sRGB-encoded values (input clamped to [0, 1]), differentiable."""
    x = x.clamp(0.0, 1.0)
    # the pow branch sees only values where it is selected or a safe constant: no inf gradient at 0
    hi = 1.055 * torch.pow(x.clamp(min=0.0031308), 1.0 / 2.4) - 0.055
    return torch.where(x <= 0.0031308, 12.92 * x, hi)


def face_adjacency(faces: np.ndarray) -> np.ndarray:
    """[P, 2] pairs of faces that share an edge (each pair once)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    fid = np.tile(np.arange(len(faces)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, fid = e[order], fid[order]
    same = (e[1:] == e[:-1]).all(axis=1)  # manifold: an edge has at most two faces, adjacent after sorting
    return np.stack([fid[:-1][same], fid[1:][same]], axis=1)


class IsometryLoss:
    """Eq. 2 of the paper: L_iso = 1/|V| sum_v 1/|N(v)| sum_{v' in N(v)} | |v1 - v1'| - |vt - vt'| |.

    The paper's formula has no absolute value (the signed sum could cancel); like Dynamic 3D
    Gaussians' isometry term (a weighted L2 of scalars) each edge's length change counts by its
    magnitude. Each undirected edge (a, b) appears in the rings of a and b, so its weight is
    (1/deg a + 1/deg b) / |V|.
    """

    def __init__(self, rest_vertices: np.ndarray, faces: np.ndarray):
        edges = mesh_edges(faces)
        V = len(rest_vertices)
        deg = np.bincount(edges.ravel(), minlength=V).astype(np.float64)
        used = deg > 0
        w = (1.0 / deg[edges[:, 0]] + 1.0 / deg[edges[:, 1]]) / max(int(used.sum()), 1)
        rest = np.linalg.norm(rest_vertices[edges[:, 0]] - rest_vertices[edges[:, 1]], axis=1)
        self.edges = torch.from_numpy(edges).long()
        self.weights = torch.from_numpy(w).float()
        self.rest = torch.from_numpy(rest).float()

    def __call__(self, vertices: torch.Tensor) -> torch.Tensor:
        d = vertices[self.edges[:, 0]] - vertices[self.edges[:, 1]]
        length = torch.sqrt((d * d).sum(-1) + 1e-20)
        return (self.weights.to(vertices.dtype) * (length - self.rest.to(vertices.dtype)).abs()).sum()


class NormalLoss:
    """Eq. 3 of the paper: L_normal = 1/|F| sum_f sum_{f' in N(f)} (1 - n(f) . n(f')).

    N(f) are the faces sharing an edge with f; every adjacent pair appears twice in the double
    sum, hence the factor 2 over the list of unique pairs. Zero exactly for a flat mesh.


    ``rest_vertices`` given: the "rest" variant, 2/|F| sum_pairs |cos_t - cos_1|, the change of
    each dihedral's cosine since frame 1. The paper's meshes (ActorHQ scans) are dense, so its
    plain term is a small smoothness prior; on a coarse template (a 1,229-vertex body, 2 cm cloth
    edges) the plain term is dominated by the template's own curvature and flattens it, while the
    rest variant is zero for any rigid motion and for the template itself and still penalises the
    noisy creases the paper's Fig. 10 shows.
    """

    def __init__(self, faces: np.ndarray, rest_vertices: np.ndarray | None = None):
        self.faces = torch.from_numpy(np.asarray(faces)).long()
        self.pairs = torch.from_numpy(face_adjacency(np.asarray(faces))).long()
        self.n_faces = len(faces)
        self.rest_cos = None
        if rest_vertices is not None:
            self.rest_cos = self.cosines(torch.from_numpy(np.asarray(rest_vertices, np.float64))).float()

    def cosines(self, vertices: torch.Tensor) -> torch.Tensor:
        """[P] n(f) . n(f') per adjacent pair."""
        tri = vertices[self.faces]
        n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n = n / torch.sqrt((n * n).sum(-1, keepdim=True) + 1e-30)
        return (n[self.pairs[:, 0]] * n[self.pairs[:, 1]]).sum(-1)

    def __call__(self, vertices: torch.Tensor) -> torch.Tensor:
        cos = self.cosines(vertices)
        if self.rest_cos is None:
            return 2.0 * (1.0 - cos).sum() / self.n_faces
        return 2.0 * (cos - self.rest_cos.to(cos.dtype)).abs().sum() / self.n_faces


class CollisionLoss:
    """Garment-body collision penalty (the official PhysAvatar code adds one; the paper's Eq. 4 does not):
    mean over garment vertices of relu(margin - d)^2 / margin^2, d the signed distance from the
    closest point of the body surface along that triangle's normal (pairs fixed for one frame).

    The body is known from the capture's poses, so it sits where skinning puts it; the garment
    sinking into it is the easiest way for a photometric fit to slide an unobserved fold.
    The closest point is taken on the body's triangles, not at its closest vertex: on a coarse
    collider (2-3 cm faces) the plane through the closest vertex with its averaged normal lies
    outside the surface between vertices, so a garment resting on the body would be penalised
    and pushed out by centimetres.

    Args:
        garment: [G] garment vertex indices. body: [B] body vertex indices.
        body_faces: [Fb, 3] faces over the full vertex array whose vertices are all body.
        margin: metres.
        k: closest body vertices whose incident faces are searched for the closest point.
    """

    def __init__(self, garment: np.ndarray, body: np.ndarray, body_faces: np.ndarray, margin: float = 0.001,
                 k: int = 4):
        self.garment = torch.from_numpy(np.asarray(garment)).long()
        self.body = np.asarray(body)
        self.body_faces = np.asarray(body_faces)
        self.margin = margin
        self.k = min(k, len(self.body))
        n = int(max(self.body_faces.max(initial=0), self.body.max(initial=0))) + 1
        ring = [[] for _ in range(n)]
        for fi, f in enumerate(self.body_faces):
            for v in f:
                ring[v].append(fi)
        self.incident = np.full((n, max(1, max(len(r) for r in ring))), -1)  # [n, W] body faces per vertex, -1 pad
        for v, r in enumerate(ring):
            self.incident[v, :len(r)] = r
        self.points = self.normals = None

    def update(self, vertices: np.ndarray) -> None:
        """Pair every garment vertex with its closest point on the body at ``vertices`` [V, 3]."""
        from scipy.spatial import cKDTree
        from trimesh.triangles import closest_point

        V = np.asarray(vertices, np.float64)
        x = V[self.garment.numpy()]
        _, j = cKDTree(V[self.body]).query(x, k=self.k)
        cand = self.incident[self.body[np.asarray(j).reshape(len(x), -1)]].reshape(len(x), -1)  # [G, C]
        valid = cand >= 0
        cand = np.where(valid, cand, 0)
        G, C = cand.shape
        cp = closest_point(V[self.body_faces[cand.ravel()]], np.repeat(x, C, axis=0)).reshape(G, C, 3)
        d2 = np.where(valid, ((cp - x[:, None]) ** 2).sum(-1), np.inf)
        best = d2.argmin(1)
        face = self.body_faces[cand[np.arange(G), best]]
        n = np.cross(V[face[:, 1]] - V[face[:, 0]], V[face[:, 2]] - V[face[:, 0]])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-30
        self.points = torch.from_numpy(cp[np.arange(G), best]).float()
        self.normals = torch.from_numpy(n).float()

    def __call__(self, vertices: torch.Tensor) -> torch.Tensor:
        d = ((vertices[self.garment] - self.points.to(vertices.dtype)) * self.normals.to(vertices.dtype)).sum(-1)
        return (torch.relu(self.margin - d) ** 2).mean() / self.margin**2


class AnchorLoss:
    """Mean squared distance of some vertices from given targets, in units of ``scale`` [m]:
    mean_i ||x_i - a_i||^2 / scale^2 (the body and the garment's boundary held near the
    capture's body pose)."""

    def __init__(self, index: np.ndarray, scale: float = 0.01):
        self.index = torch.from_numpy(np.asarray(index)).long()
        self.scale = scale
        self.targets = None

    def update(self, vertices: np.ndarray) -> None:
        self.targets = torch.from_numpy(np.asarray(vertices, np.float32)[self.index.numpy()])

    def __call__(self, vertices: torch.Tensor) -> torch.Tensor:
        d = vertices[self.index] - self.targets.to(vertices.dtype)
        return (d * d).sum(-1).mean() / self.scale**2
