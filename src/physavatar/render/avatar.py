"""The render meshes of a labelled avatar template: the one place that turns a template (faces,
labels, atlas UVs) and any frame's vertices into :class:`MeshSpec`\\ s.

The body is one-sided and the garments two-sided (their insides are seen through openings), as
the synthetic captures are rendered; both sample one texture atlas. A template with one label
only (or no labels) becomes a single two-sided mesh ``avatar`` (a closed body's inside is never
seen anyway). Faces whose vertices carry different labels belong to neither part.

Build once, then place per frame (the split at UV seams is done once)::

    meshes = AvatarMeshes.build(template.vertices, template.faces, template.face_uvs, template.labels)
    specs = meshes.specs(vertices_of_frame_t, texture)          # [MeshSpec]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import split_uv_seams, submesh
from .mesh import MeshSpec


@dataclass(frozen=True)
class AvatarMeshes:
    """The template split into Mitsuba meshes.

    Attributes:
        names: mesh names (``body``, ``garment`` or ``avatar``), in scene order.
        faces: name -> [F', 3] faces of that mesh's vertices.
        uvs: name -> [V', 2] per-vertex atlas coordinates (split at UV seams), or None when built
            without ``face_uvs``.
        vertex_maps: name -> [V'] template vertex of each mesh vertex: ``vertices[vertex_maps[n]]``
            are mesh ``n``'s positions at template-vertex positions ``vertices``.
        twosided: name -> bool.
    """

    names: tuple[str, ...]
    faces: dict
    uvs: dict
    vertex_maps: dict
    twosided: dict

    @staticmethod
    def build(template_vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray | None = None,
              labels: np.ndarray | None = None) -> "AvatarMeshes":
        """Split ``faces`` [F, 3] of a [V, 3] template by ``labels`` [V] (0 body, >0 garment).

        ``face_uvs`` [F, 3, 2] (the atlas) makes textured meshes, with vertices split at UV
        seams; without it (untextured renders) the vertices are not split, so smooth normals
        stay continuous across seams.
        """
        n = len(template_vertices)
        garment = np.zeros(n, bool) if labels is None else np.asarray(labels) > 0
        parts = [("body", ~garment, False), ("garment", garment, True)]
        if not garment.any() or garment.all():
            parts = [("avatar", np.ones(n, bool), True)]
        names, F, UV, M, TS = [], {}, {}, {}, {}
        for name, sel, twosided in parts:
            fsel = sel[faces].all(1)
            if not fsel.any():
                continue
            idx, sub_faces = submesh(faces, sel)
            if face_uvs is not None:
                sm = split_uv_seams(np.asarray(template_vertices)[idx], sub_faces, np.asarray(face_uvs)[fsel])
                F[name], UV[name], M[name] = sm.faces, sm.uvs, idx[sm.vertex_map]
            else:
                F[name], UV[name], M[name] = sub_faces, None, idx
            names.append(name)
            TS[name] = twosided
        return AvatarMeshes(tuple(names), F, UV, M, TS)

    def specs(self, vertices: np.ndarray, texture: np.ndarray | None = None,
              reflectance=(0.6, 0.6, 0.6)) -> list[MeshSpec]:
        """[MeshSpec] at template-vertex positions ``vertices`` [V, 3], sampling ``texture``
        [H, W, 3] (linear albedo; needs the meshes built with ``face_uvs``), or with the constant
        linear ``reflectance`` when ``texture`` is None."""
        out = []
        for n in self.names:
            v = vertices[self.vertex_maps[n]]
            if texture is not None:
                if self.uvs[n] is None:
                    raise ValueError("a textured avatar needs meshes built with face_uvs")
                out.append(MeshSpec(n, v, self.faces[n], uvs=self.uvs[n], texture=texture, twosided=self.twosided[n]))
            else:
                out.append(MeshSpec(n, v, self.faces[n], reflectance=tuple(reflectance), twosided=self.twosided[n]))
        return out
