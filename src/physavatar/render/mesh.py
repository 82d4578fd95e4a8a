"""Triangle meshes from numpy arrays as in-memory Mitsuba meshes (UV seams: ``geometry.split_uv_seams``).

A :class:`MeshSpec` is plain data (arrays plus material choices); :func:`to_mitsuba_mesh` builds
the ``mi.Mesh`` by filling its buffers through ``mi.traverse`` (no temporary PLY/OBJ files).

UV convention: the OBJ / trimesh one, ``v = 0`` at the bottom row of the texture image and
``v = 1`` at the top (row 0). Mitsuba's bitmap lookup puts ``v = 0`` at row 0, so ``v`` is flipped
when the buffers are filled, exactly as Mitsuba's own OBJ loader does. Texture and vertex colors
are linear reflectances in [0, 1] (convert sRGB images with ``image.srgb_to_linear`` first).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .backend import mitsuba


@dataclass(frozen=True)
class MeshSpec:
    """One diffuse mesh of a scene.

    Attributes:
        name: Mitsuba id; parameter keys start with it (``"<name>.bsdf.reflectance.data"``).
            Letters, digits and underscores.
        vertices: [V, 3] world positions (metres).
        faces: [F, 3] vertex indices, counter-clockwise seen from the front side.
        colors: [V, 3] linear per-vertex reflectance, or None.
        uvs: [V, 2] per-vertex texture coordinates (OBJ convention), required with ``texture``.
            Meshes with per-corner UVs go through :func:`split_uv_seams` first.
        texture: [Ht, Wt, 3] linear reflectance image (row 0 = top = v 1), or None.
        reflectance: constant linear RGB used when neither ``colors`` nor ``texture`` is given.
        twosided: shade both sides alike (open garments seen from inside); one-sided diffuse
            surfaces are black from the back.
        smooth: interpolate vertex normals (Phong shading) instead of flat face normals.
    """

    name: str
    vertices: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    colors: np.ndarray | None = field(default=None, repr=False)
    uvs: np.ndarray | None = field(default=None, repr=False)
    texture: np.ndarray | None = field(default=None, repr=False)
    reflectance: tuple[float, float, float] = (0.5, 0.5, 0.5)
    twosided: bool = False
    smooth: bool = True

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("_", "a").isalnum():
            raise ValueError(f"mesh name {self.name!r}: use letters, digits and underscores")
        v = np.asarray(self.vertices, dtype=np.float64)
        f = np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"mesh {self.name!r}: vertices must be [V, 3], got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"mesh {self.name!r}: faces must be integer [F, 3], got {f.dtype} {f.shape}")
        if not np.isfinite(v).all():
            raise ValueError(f"mesh {self.name!r}: vertices contain non-finite values")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"mesh {self.name!r}: face index out of range [0, {len(v)})")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f.astype(np.int64))
        if self.colors is not None:
            c = np.asarray(self.colors, dtype=np.float64)
            if c.shape != v.shape:
                raise ValueError(f"mesh {self.name!r}: colors must be [V, 3] = {v.shape}, got {c.shape}")
            object.__setattr__(self, "colors", c)
        if self.uvs is not None:
            uv = np.asarray(self.uvs, dtype=np.float64)
            if uv.shape != (len(v), 2):
                raise ValueError(
                    f"mesh {self.name!r}: uvs must be per-vertex [V, 2] = ({len(v)}, 2), got {uv.shape}; "
                    "per-corner UVs need split_uv_seams first"
                )
            object.__setattr__(self, "uvs", uv)
        if self.texture is not None:
            t = np.asarray(self.texture, dtype=np.float32)
            if t.ndim != 3 or t.shape[2] != 3:
                raise ValueError(f"mesh {self.name!r}: texture must be [Ht, Wt, 3], got {t.shape}")
            if self.uvs is None:
                raise ValueError(f"mesh {self.name!r}: a texture needs uvs")
            if self.colors is not None:
                raise ValueError(f"mesh {self.name!r}: give colors or a texture, not both")
            object.__setattr__(self, "texture", t)
        object.__setattr__(self, "reflectance", tuple(float(x) for x in np.broadcast_to(self.reflectance, 3)))

    @property
    def material(self) -> str:
        """``"texture"``, ``"vertex_color"`` or ``"constant"``."""
        if self.texture is not None:
            return "texture"
        if self.colors is not None:
            return "vertex_color"
        return "constant"

    def with_vertices(self, vertices: np.ndarray) -> "MeshSpec":
        """The same mesh and material at new vertex positions (one tracked / simulated frame)."""
        from dataclasses import replace

        return replace(self, vertices=vertices)


def bsdf_dict(spec: MeshSpec) -> dict:
    """Mitsuba BSDF dict of ``spec``'s material: diffuse, optionally wrapped in ``twosided``."""
    mi = mitsuba()
    if spec.material == "texture":
        reflectance = {
            "type": "bitmap",
            "data": mi.TensorXf(np.ascontiguousarray(spec.texture, dtype=np.float32)),
            # The array already holds linear reflectance: no sRGB decoding, no spectral upsampling.
            "raw": True,
            "filter_type": "bilinear",
            # Clamp rather than repeat: a UV atlas's border texels must not blend with the
            # opposite border.
            "wrap_mode": "clamp",
        }
    elif spec.material == "vertex_color":
        reflectance = {"type": "mesh_attribute", "name": "vertex_color"}
    else:
        reflectance = {"type": "rgb", "value": list(spec.reflectance)}
    bsdf = {"type": "diffuse", "reflectance": reflectance}
    return {"type": "twosided", "bsdf": bsdf} if spec.twosided else bsdf


def to_mitsuba_mesh(spec: MeshSpec):
    """An in-memory ``mi.Mesh`` with ``spec``'s buffers and BSDF."""
    mi = mitsuba()
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf_dict(spec))
    has_uv = spec.uvs is not None
    mesh = mi.Mesh(
        spec.name,
        vertex_count=len(spec.vertices),
        face_count=len(spec.faces),
        props=props,
        has_vertex_normals=spec.smooth,
        has_vertex_texcoords=has_uv,
    )
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(spec.vertices.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(spec.faces.astype(np.uint32).ravel())
    if has_uv:
        uv = spec.uvs.astype(np.float32).copy()
        uv[:, 1] = 1.0 - uv[:, 1]  # OBJ convention (v up) -> Mitsuba's (v down), see module doc
        params["vertex_texcoords"] = mi.Float(uv.ravel())
    if spec.colors is not None:
        mesh.add_attribute("vertex_color", 3, mi.Float(spec.colors.astype(np.float32).ravel()))
    # update() rebuilds the bounding box and, with has_vertex_normals, the area-weighted normals.
    params.update()
    return mesh
