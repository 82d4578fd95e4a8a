"""Mesh-aligned Gaussians: one flat Gaussian per template face (or per face of its midpoint
subdivision), rendered by :mod:`physavatar.splat` (the numba kernels, or gsplat on CUDA)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ...camera import Camera
from ...splat import longest_edge_index, mesh_to_gaussians, rasterize
from ...splat.rasterize import resolve_backend


@dataclass
class MeshGaussians:
    """Per-face Gaussian parameters of a template (the vertices live outside).

    Attributes:
        faces: [F, 3] long. edge_index: [F] the face frames' x edge (longest edge of frame 1).
        colors: [F, 3] linear RGB. log_scales: [F, 2]. opacity_logits: [F].
    """

    faces: torch.Tensor
    edge_index: torch.Tensor
    colors: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    midpoints: list = field(default_factory=list)  # per subdivision level: [E, 2] edge endpoints
    antialiased: bool = False  # mass-conserving low-pass (:func:`physavatar.splat.rasterize`)
    backend: str = "numba"  # the rasterizer (:func:`physavatar.splat.rasterize`'s ``backend``)

    @staticmethod
    def init(vertices: np.ndarray, faces: np.ndarray, subdivide: int = 0, opacity: float = 0.88,
             antialiased: bool = False, backend: str = "numba") -> MeshGaussians:
        """Gaussians of ``faces``, or of their ``subdivide``-times midpoint subdivision (4^k per face),
        all with opacity ``opacity``."""
        faces = np.asarray(faces, np.int64)
        mids = []
        for _ in range(subdivide):
            faces, m = _midpoint_subdivide(faces, len(vertices) + sum(len(x) for x in mids))
            mids.append(m)
        model = MeshGaussians(torch.from_numpy(faces), torch.zeros(0), torch.zeros(0), torch.zeros(0), torch.zeros(0),
                              [torch.from_numpy(m) for m in mids], antialiased, resolve_backend(backend))
        V = model.gaussian_vertices(torch.from_numpy(np.asarray(vertices, np.float32)))
        tri = V[model.faces]
        area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
        # sigma = 0.45 sqrt(area) is 0.3 of an equilateral face's side: neighbouring splats
        # overlap enough to close the surface without bleeding far past the face.
        s = (0.45 * area.clamp(min=1e-12).sqrt()).log()
        model.edge_index = longest_edge_index(V, model.faces)
        model.colors = torch.full((len(model.faces), 3), 0.2)
        model.log_scales = torch.stack([s, s], dim=1)
        model.opacity_logits = torch.full((len(model.faces),), float(np.log(opacity / (1.0 - opacity))))
        return model

    def gaussian_vertices(self, vertices: torch.Tensor) -> torch.Tensor:
        """[V', 3] the vertices of the (subdivided) Gaussian mesh: linear in ``vertices``."""
        for m in self.midpoints:
            vertices = torch.cat([vertices, 0.5 * (vertices[m[:, 0]] + vertices[m[:, 1]])])
        return vertices

    def face_colors(self, n_faces: int) -> np.ndarray:
        """[F, 3] per template face: the mean colour of its 4^k sub-faces (subdivision keeps
        each face's children contiguous)."""
        c = self.colors.numpy()
        return c.reshape(n_faces, -1, 3).mean(1).astype(np.float32)

    def splats(self, vertices: torch.Tensor, colors: torch.Tensor | None = None,
               log_scales: torch.Tensor | None = None, opacity_logits: torch.Tensor | None = None) -> tuple:
        """(means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colors [N, 3]) of the
        Gaussians on ``vertices`` [V, 3]; computed once per step and shared by every view
        (building them per view multiplied the autograd graph by the number of cameras)."""
        means, quats, scales = mesh_to_gaussians(
            self.gaussian_vertices(vertices), self.faces, self.log_scales if log_scales is None else log_scales, self.edge_index)
        col = (self.colors if colors is None else colors).clamp(0.0, 1.0)
        op = torch.sigmoid(self.opacity_logits if opacity_logits is None else opacity_logits)
        return means, quats, scales, op, col

    def rasterize(self, splats: tuple, cam: Camera) -> dict:
        """Rasterize :meth:`splats` into ``cam``: rgb [H, W, 3] linear (over black), alpha [H, W]."""
        return rasterize(*splats, torch.from_numpy(cam.w2c.astype(np.float32)), torch.from_numpy(cam.K.astype(np.float32)),
                         cam.width, cam.height, backend=self.backend, antialiased=self.antialiased)

    def render(self, vertices: torch.Tensor, cam: Camera, colors: torch.Tensor | None = None,
               log_scales: torch.Tensor | None = None, opacity_logits: torch.Tensor | None = None) -> dict:
        """Rasterize into ``cam``: rgb [H, W, 3] linear (over black), alpha [H, W]."""
        return self.rasterize(self.splats(vertices, colors, log_scales, opacity_logits), cam)


def _midpoint_subdivide(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Split each triangle into four at its edge midpoints.

    Returns the new faces [4F, 3] (face f's children at rows 4f..4f+3) and the midpoints' edge
    endpoints [E, 2]; midpoint e gets vertex index n_vertices + e.
    """
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    uniq, inv = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True)
    inv = inv.reshape(3, -1).T + n_vertices  # [F, 3] midpoint of edge (0,1), (1,2), (2,0)
    a, b, c = faces.T
    ab, bc, ca = inv.T
    new = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                    np.stack([ab, bc, ca], 1)], 1).reshape(-1, 3)
    return new, uniq

