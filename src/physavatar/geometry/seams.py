"""Splitting vertices along UV seams, so per-corner texture coordinates become per-vertex
(renderers and glTF interpolate per-vertex attributes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SplitMesh:
    """Result of :func:`split_uv_seams`.

    Attributes:
        vertices: [V', 3] positions, ``vertices[i] = original_vertices[vertex_map[i]]``.
        faces: [F, 3] indices into the split vertices (same face order as the input).
        uvs: [V', 2] one texture coordinate per split vertex.
        vertex_map: [V'] index of each split vertex in the original vertex array; positions of
            a later frame of the original mesh map over with ``new_positions[vertex_map]``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    vertex_map: np.ndarray


def split_uv_seams(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, uv_faces: np.ndarray | None = None) -> SplitMesh:
    """Give each distinct (vertex, uv) pair its own vertex, so UVs become per-vertex.

    A vertex on a UV seam has one position but two or more texture coordinates; renderers
    interpolate per-vertex attributes, so such a vertex is duplicated once per distinct UV.

    Args:
        vertices: [V, 3] positions.
        faces: [F, 3] vertex indices.
        uvs: either [F, 3, 2] per-corner texture coordinates (``uv_faces`` None; corners are the
            same UV when their values are bit-identical), or [T, 2] texture coordinates indexed by
            ``uv_faces`` (the OBJ ``f v/vt`` layout).
        uv_faces: [F, 3] indices into ``uvs``, or None.
    Returns:
        :class:`SplitMesh`. Split vertices are ordered by original vertex index, so a mesh
        without seams comes back with its vertex order unchanged.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    uvs = np.asarray(uvs, dtype=np.float64)
    F = len(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be [F, 3], got {faces.shape}")
    if uv_faces is None:
        if uvs.shape != (F, 3, 2):
            raise ValueError(f"per-corner uvs must be [F, 3, 2] = ({F}, 3, 2), got {uvs.shape}")
        corner_uv = uvs.reshape(-1, 2)
        # Compare UVs by their bit patterns: exact equality, and +0.0 / -0.0 never come from atlases.
        bits = np.ascontiguousarray(corner_uv).view(np.int64).reshape(-1, 2)
        keys = np.column_stack([faces.reshape(-1), bits])
    else:
        uv_faces = np.asarray(uv_faces, dtype=np.int64)
        if uv_faces.shape != faces.shape:
            raise ValueError(f"uv_faces must be [F, 3] like faces, got {uv_faces.shape}")
        if uvs.ndim != 2 or uvs.shape[1] != 2 or uv_faces.min() < 0 or uv_faces.max() >= len(uvs):
            raise ValueError("uvs must be [T, 2] and uv_faces must index into it")
        corner_uv = uvs[uv_faces.reshape(-1)]
        keys = np.column_stack([faces.reshape(-1), uv_faces.reshape(-1)])
    # np.unique sorts rows lexicographically, first column (the original vertex) first.
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    vertex_map = faces.reshape(-1)[first]
    return SplitMesh(
        vertices=vertices[vertex_map],
        faces=inverse.reshape(F, 3).astype(np.int64),
        uvs=corner_uv[first],
        vertex_map=vertex_map.astype(np.int64),
    )
