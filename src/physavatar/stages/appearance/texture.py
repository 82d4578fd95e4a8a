"""The texture atlas: an automatic UV unwrap (when the template has none), which face each texel
belongs to, and the initial texture splatted from per-face colours.

Shapes follow docs/rendering.md: textures are [H, W, 3] linear, row 0 = v 1 (OBJ convention).
"""

from __future__ import annotations

import numpy as np


def uv_atlas(vertices: np.ndarray, faces: np.ndarray, texture_size: int = 1024, padding: int = 2) -> np.ndarray:
    """Automatic UV atlas with xatlas, every chart counter-clockwise (not mirrored).

    xatlas's parametrization mirrors some charts (a texture painted on them would read
    backwards, and the sign of the UV area flips). Charts are therefore made once, the mirrored
    ones reflected, and the charts packed again from these UVs; rotations stay off in both
    packings because xatlas's chart rotation can mirror too.

    Args:
        vertices: [V, 3]; faces: [F, 3] counter-clockwise seen from outside.
        texture_size: the atlas is packed for this resolution, ``padding`` texels between charts
            so that bilinear lookups never blend two charts.
    Returns:
        [F, 3, 2] per-corner UVs in [0, 1] (OBJ convention, v up), faces in the input order.
    """
    import scipy.sparse as sp
    import xatlas
    from scipy.sparse.csgraph import connected_components

    def pack_options():
        pack = xatlas.PackOptions()
        pack.resolution = int(texture_size)
        pack.padding = int(padding)
        pack.bilinear = True
        pack.rotate_charts = False
        pack.rotate_charts_to_axis = False
        return pack

    faces = np.asarray(faces)
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.uint32))
    atlas.generate(pack_options=pack_options())
    vmap, indices, uvs = atlas[0]
    if indices.shape != faces.shape or not np.array_equal(vmap[indices], faces):
        # xatlas keeps the face order; if a version ever reorders, the per-face data would not
        # line up with the template, so refuse rather than silently scramble colours.
        raise RuntimeError("xatlas changed the face order or topology of the mesh")
    area = _uv_signed_area(uvs[indices])
    F = len(faces)
    inc = sp.csr_matrix((np.ones(3 * F), (np.repeat(np.arange(F), 3), indices.ravel())), shape=(F, len(uvs)))
    _, chart = connected_components(inc @ inc.T, directed=False)
    chart_area = np.bincount(chart, weights=area)
    mirrored = np.zeros(len(uvs), bool)
    mirrored[indices[chart_area[chart] < 0].ravel()] = True
    if mirrored.any():
        uv2 = uvs.astype(np.float64).copy()
        uv2[mirrored, 0] = -uv2[mirrored, 0]
        repack = xatlas.Atlas()
        repack.add_uv_mesh(uv2.astype(np.float32), np.ascontiguousarray(indices, dtype=np.uint32))
        repack.generate(pack_options=pack_options())
        vmap2, indices2, uvs = repack[0]
        if not np.array_equal(vmap2[indices2], indices):
            raise RuntimeError("xatlas changed the face order while repacking")
        indices = indices2
    out = np.asarray(uvs, dtype=np.float64)[indices]
    if (_uv_signed_area(out) <= 0).any():
        raise RuntimeError("xatlas produced flipped UV triangles")
    return out


def _uv_signed_area(face_uvs: np.ndarray) -> np.ndarray:
    """[F] signed area of UV triangles (positive: counter-clockwise, v up)."""
    a, b, c = face_uvs[:, 0], face_uvs[:, 1], face_uvs[:, 2]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]))


def texel_face_map(face_uvs: np.ndarray, size: int) -> np.ndarray:
    """[size, size] int64: the face whose UV triangle contains each texel centre, -1 for none.

    Texel (row r, column c) has its centre at u = (c + ½)/size, v = 1 - (r + ½)/size (row 0 =
    v 1). Centres on a shared edge go to one of the two faces; where UV triangles overlap (an
    atlas that mirrors halves onto the same texels) the later face wins.
    """
    return texel_barycentrics(face_uvs, size)[0]


def texel_barycentrics(face_uvs: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`texel_face_map` and the barycentric coordinates of each texel centre in its face.

    Returns:
        fmap [size, size] int64 (-1: no face); bary [size, size, 3] float64 weights of the face's
        corners (0 where fmap is -1), so ``Σ_k bary[..., k] · X[faces[fmap, k]]`` is the surface
        point of a texel for any per-vertex quantity X.
    """
    size = int(size)
    uv = np.asarray(face_uvs, np.float64)
    # texel coordinates: x = u·size - ½, y = (1 - v)·size - ½, so the centre of (r, c) is (c, r)
    x = uv[..., 0] * size - 0.5
    y = (1.0 - uv[..., 1]) * size - 0.5
    out = -np.ones((size, size), np.int64)
    bary = np.zeros((size, size, 3))
    x0 = np.clip(np.ceil(x.min(1)), 0, size - 1).astype(np.int64)
    x1 = np.clip(np.floor(x.max(1)), -1, size - 1).astype(np.int64)
    y0 = np.clip(np.ceil(y.min(1)), 0, size - 1).astype(np.int64)
    y1 = np.clip(np.floor(y.max(1)), -1, size - 1).astype(np.int64)
    for f in np.flatnonzero((x1 >= x0) & (y1 >= y0)):
        cx, cy = np.meshgrid(np.arange(x0[f], x1[f] + 1), np.arange(y0[f], y1[f] + 1))
        (ax, bx, qx), (ay, by, qy) = x[f], y[f]
        det = (bx - ax) * (qy - ay) - (qx - ax) * (by - ay)
        if det == 0:
            continue
        l1 = ((cx - ax) * (qy - ay) - (qx - ax) * (cy - ay)) / det
        l2 = ((bx - ax) * (cy - ay) - (cx - ax) * (by - ay)) / det
        inside = (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)
        out[cy[inside], cx[inside]] = f
        bary[cy[inside], cx[inside]] = np.stack([1 - l1[inside] - l2[inside], l1[inside], l2[inside]], -1)
    return out, bary


def fill_empty(texture: np.ndarray, filled: np.ndarray) -> np.ndarray:
    """Copy to every texel where ``filled`` is False the value of the nearest filled texel
    (dilation to convergence), so bilinear lookups near chart borders stay on-chart."""
    from scipy.ndimage import distance_transform_edt

    if filled.all() or not filled.any():
        return texture.copy()
    _, (ri, ci) = distance_transform_edt(~filled, return_indices=True)
    return texture[ri, ci]


def splat_face_colors(face_uvs: np.ndarray, face_colors: np.ndarray, size: int,
                      valid: np.ndarray | None = None) -> np.ndarray:
    """Initial texture: each face's colour in that face's texels, empty texels dilated.

    Args:
        face_uvs: [F, 3, 2]; face_colors: [F, 3] linear RGB.
        valid: [F] bool, faces whose colour is known (the others are filled from neighbours).
    Returns:
        [size, size, 3] float32 linear texture.
    """
    fmap = texel_face_map(face_uvs, size)
    ok = fmap >= 0
    if valid is not None:
        ok &= np.asarray(valid, bool)[np.maximum(fmap, 0)]
    tex = np.zeros((size, size, 3), np.float32)
    tex[ok] = np.asarray(face_colors, np.float32)[fmap[ok]]
    return np.clip(fill_empty(tex, ok), 0.0, 1.0).astype(np.float32)
