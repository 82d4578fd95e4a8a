"""Rest-state geometry of a cloth mesh: triangle frames, hinges, lumped areas.

Everything the elastic energies need that depends only on the rest mesh is computed once here
(vectorised, no loops over elements).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import PhysavatarError


@dataclasses.dataclass(frozen=True)
class ClothTopology:
    """Rest geometry of a triangle mesh.

    Attributes:
        rest: [N, 3] rest vertex positions.
        faces: [F, 3] int64 triangles.
        edges: [E, 2] unique undirected edges (sorted pairs).
        hinges: [H, 4] interior edges as (x0, x1, x2, x3): x0–x1 the shared edge, x2 opposite
            in the face that runs x0→x1, x3 opposite in the face that runs x1→x0.
        face_area: [F] rest areas.
        face_grad: [F, 3, 2] rows g_a with F = Σ_a x_a g_aᵀ, the deformation gradient of a
            linear triangle from its world positions to its 2D rest frame.
        vertex_area: [N] lumped (one third of each incident face) rest areas.
    """

    rest: np.ndarray
    faces: np.ndarray
    edges: np.ndarray
    hinges: np.ndarray
    face_area: np.ndarray
    face_grad: np.ndarray
    vertex_area: np.ndarray

    @classmethod
    def build(cls, rest: np.ndarray, faces: np.ndarray) -> "ClothTopology":
        """rest: [N, 3] float; faces: [F, 3] int."""
        rest = np.ascontiguousarray(rest, dtype=np.float64)
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        if rest.ndim != 2 or rest.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise PhysavatarError(None, "cloth mesh must be vertices [N, 3] and faces [F, 3]")
        if faces.size and (faces.min() < 0 or faces.max() >= len(rest)):
            raise PhysavatarError(None, "cloth faces index vertices out of range")
        e1 = rest[faces[:, 1]] - rest[faces[:, 0]]
        e2 = rest[faces[:, 2]] - rest[faces[:, 0]]
        normal = np.cross(e1, e2)
        double_area = np.linalg.norm(normal, axis=1)
        if np.any(double_area <= 1e-14 * max(1.0, np.max(np.abs(rest)) ** 2)):
            raise PhysavatarError(None, "cloth mesh has degenerate (zero-area) triangles")
        # Rest frame: e1 along the first axis. Dm = [[|e1|, e1·e2/|e1|], [0, 2A/|e1|]].
        l1 = np.linalg.norm(e1, axis=1)
        dm = np.zeros((len(faces), 2, 2))
        dm[:, 0, 0] = l1
        dm[:, 0, 1] = np.einsum("ij,ij->i", e1, e2) / l1
        dm[:, 1, 1] = double_area / l1
        b = np.linalg.inv(dm)  # F = [x1-x0, x2-x0] Dm⁻¹
        face_grad = np.stack([-(b[:, 0] + b[:, 1]), b[:, 0], b[:, 1]], axis=1)
        face_area = 0.5 * double_area
        vertex_area = np.bincount(
            faces.ravel(), weights=np.repeat(face_area / 3.0, 3), minlength=len(rest)
        )
        edges, hinges = _edges_and_hinges(faces)
        return cls(rest, faces, edges, hinges, face_area, face_grad, vertex_area)


def _edges_and_hinges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges [E, 2] and interior hinges [H, 4] (see ClothTopology)."""
    nf = len(faces)
    # Directed half-edges (a -> b) of face f, opposite vertex c.
    a = faces[:, [0, 1, 2]].ravel()
    b = faces[:, [1, 2, 0]].ravel()
    c = faces[:, [2, 0, 1]].ravel()
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * (faces.max() + 1 if nf else 1) + hi
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    unique_keys, start, counts = np.unique(key_sorted, return_index=True, return_counts=True)
    edges = np.stack([lo[order][start], hi[order][start]], axis=1)
    if np.any(counts > 2):
        raise PhysavatarError(None, "cloth mesh is non-manifold (an edge has more than two faces)")
    pair = start[counts == 2]
    h0, h1 = order[pair], order[pair + 1]  # the two half-edges of each interior edge
    # Orient each hinge by the first half-edge: x0 -> x1 in face A (opposite x2); face B runs
    # x1 -> x0 when the mesh is consistently oriented (opposite x3).
    hinges = np.stack([a[h0], b[h0], c[h0], c[h1]], axis=1)
    if np.any(a[h1] != b[h0]):
        raise PhysavatarError(None, "cloth mesh faces are not consistently oriented")
    return edges, hinges
