"""Mesh specs of a labelled, textured avatar frame: the body one-sided, garments two-sided
(their insides are seen through openings), both sampling one texture atlas."""

from __future__ import annotations

import numpy as np

from ..geometry import split_uv_seams, submesh
from .mesh import MeshSpec


def avatar_specs(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, face_uvs: np.ndarray | None,
                 texture: np.ndarray | None, reflectance=(0.6, 0.6, 0.6)) -> list[MeshSpec]:
    """[MeshSpec] for one frame.

    Args:
        vertices: [V, 3]; faces: [F, 3]; labels: [V] (0 body, >0 garment);
        face_uvs: [F, 3, 2] atlas coordinates or None; texture: [H, W, 3] linear albedo or None
            (then a constant ``reflectance``).
    """
    specs = []
    garment = np.asarray(labels) > 0
    for name, sel, twosided in (("body", ~garment, False), ("garment", garment, True)):
        fsel = sel[faces].all(1)
        if not fsel.any():
            continue
        idx, f = submesh(faces, sel)
        if texture is not None and face_uvs is not None:
            sm = split_uv_seams(vertices[idx], f, face_uvs[fsel])
            specs.append(MeshSpec(name, sm.vertices, sm.faces, uvs=sm.uvs, texture=texture, twosided=twosided))
        else:
            specs.append(MeshSpec(name, vertices[idx], f, reflectance=tuple(reflectance), twosided=twosided))
    return specs
