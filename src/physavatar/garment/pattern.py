"""Sewing-pattern panels -> one near-uniform, manifold triangle mesh.

A panel is a closed outline drawn in the frontal (x, z) plane, made of pieces (open edges and
seams, CCW), and a map lifting it to 3D (``surface.PanelSurface``). Its pattern plane is the ARAP
flattening of that lift (``flatten.FlatPanel``), so Triangle's quality carries over to 3D. Meshing:

1. Every piece is subdivided at the target edge length measured in 3D. A seam is subdivided
   once, so the two panels it joins get identical vertices along it.
2. Shewchuk's Triangle meshes the panel with a minimum angle (``q``), no Steiner points on the
   outline (``Y``, which keeps seams identical), and a maximum area that is refined twice with the
   per-triangle 3D/2D area ratio of the lift, so triangles are near-equal in 3D, not in 2D.
3. Interior vertices are relaxed towards the area-weighted centroid of their triangles in 3D
   (centroidal smoothing), moved in pattern space through the pseudo-inverse of the lift's
   Jacobian so they stay on the garment surface and keep their UVs.
4. Seam vertices of different panels at the same frontal-plane point are merged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import triangle as tr

EQ_AREA = np.sqrt(3.0) / 4.0  # area of the equilateral triangle of unit edge
# Triangle's maximum-area bound gives triangles of about 0.6x the bound on average; this factor
# makes the mean edge come out at the requested length.
AREA_SLACK = 1.6


@dataclass
class Piece:
    """One edge of a panel outline: [n, 2] pattern points from its start corner to its end corner."""

    points: np.ndarray
    seam: str | None = None  # seam id shared by the two panels it joins; None for an open edge
    tag: str = ""  # name for boundary selection ("hem", "waist", "neck", ...)


@dataclass
class Panel:
    name: str
    pieces: list[Piece]  # counter-clockwise in the pattern plane, consecutive pieces share corners
    surface: object  # callable [n, 2] -> [n, 3] with .jacobian
    flip: bool = False  # flip faces so normals point away from the body
    mirror_uv: bool = False  # lay out mirrored in u (back panels seen from behind)


@dataclass
class PanelMesh:
    xz: np.ndarray  # [n, 2] pattern (flattened) coordinates
    tris: np.ndarray  # [m, 3]
    fixed: np.ndarray  # [n] bool: outline vertices
    seam_key: list  # per outline vertex: seam merge key (rounded pattern point) or None
    tags: list = field(default_factory=list)  # per outline vertex: piece tag
    seam_xz: list = field(default_factory=list)  # per outline vertex: frontal (x, z) on a seam, or None
    lift: object = None  # pattern -> 3D (flatten.FlatPanel)


def _densify(p, step=0.002):
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    t = np.r_[0, np.cumsum(seg)]
    tt = np.linspace(0, t[-1], max(2, int(np.ceil(t[-1] / step)) + 1))
    out = np.c_[np.interp(tt, t, p[:, 0]), np.interp(tt, t, p[:, 1])]
    out[0], out[-1] = p[0], p[-1]
    return out


def _triangle_areas3(P, T):
    return 0.5 * np.linalg.norm(np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]), axis=1)


def _signed_area2(X, T):
    a, b, c = X[T[:, 0]], X[T[:, 1]], X[T[:, 2]]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


def _arc_params(points: np.ndarray, lift, h: float) -> np.ndarray:
    """Frontal arc-length parameters of points spaced equally by the 3D arc length of a polyline."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    t2 = np.r_[0.0, np.cumsum(seg)]
    td = np.linspace(0.0, t2[-1], max(8, int(np.ceil(t2[-1] / 0.001))))
    dense = np.c_[np.interp(td, t2, points[:, 0]), np.interp(td, t2, points[:, 1])]
    s3 = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(lift(dense), axis=0), axis=1))]
    n = max(1, int(round(s3[-1] / h)))
    return np.interp(np.linspace(0.0, s3[-1], n + 1), s3, td)


def mesh_panel(panel: Panel, h: float, seam_lift, min_angle: float = 30.0, relax_iters: int = 40) -> PanelMesh:
    """Triangulate one panel at 3D edge length ``h`` (see module doc)."""
    from .flatten import FlatPanel

    spacing = float(np.clip(h / 3.0, 0.005, 0.01))  # no finer than the body raster
    polys = [np.asarray(pc.points, float) for pc in panel.pieces]
    dense = [_densify(p, spacing) for p in polys]
    outline = np.concatenate([d[:-1] for d in dense])
    flat = FlatPanel(outline, panel.surface, spacing)
    uv_l, fr_l, tag_l, seam_l = [], [], [], []
    start = 0
    for pc, poly, d in zip(panel.pieces, polys, dense):
        idx = (start + np.arange(len(d))) % len(outline)
        start += len(d) - 1
        t_d = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(d, axis=0), axis=1))]
        if pc.seam is not None:
            # subdivided along the seam curve itself, so both panels it joins get the same points
            t = _arc_params(poly, seam_lift, h)
        else:
            t = _arc_params(d, panel.surface, h)
        uv = np.c_[np.interp(t, t_d, flat.uv[idx, 0]), np.interp(t, t_d, flat.uv[idx, 1])]
        fr = np.c_[np.interp(t, t_d, d[:, 0]), np.interp(t, t_d, d[:, 1])]
        fr[0], fr[-1] = poly[0], poly[-1]
        uv_l.append(uv[:-1]), fr_l.append(fr[:-1])
        tag_l += [pc.tag] * (len(t) - 1)
        seam_l += [pc.seam is not None] * (len(t) - 1)
    loop = np.concatenate(uv_l)
    fr = np.concatenate(fr_l)
    n_out = len(loop)
    on_seam = np.array(seam_l)
    # a piece's end corner is the next piece's first point: merged if either piece is a seam
    firsts = np.cumsum([0] + [len(u) for u in uv_l[:-1]])
    on_seam[firsts] |= np.roll(np.array([pc.seam is not None for pc in panel.pieces]), 1)
    keys = [tuple(np.round(fr[i], 9)) if on_seam[i] else None for i in range(n_out)]
    seam_xz = [fr[i] if on_seam[i] else None for i in range(n_out)]
    tags = tag_l
    seg = np.c_[np.arange(n_out), (np.arange(n_out) + 1) % n_out]
    a3 = AREA_SLACK * EQ_AREA * h * h
    # pass 1 with the 2D bound (the lift only stretches: 3D area >= 2D area), then refine with the
    # local stretch so that the bound holds in 3D
    out = tr.triangulate({"vertices": loop, "segments": seg}, f"pq{min_angle:g}a{a3:.10f}YQ")
    for _ in range(2):
        X, T = out["vertices"], out["triangles"]
        J = _triangle_areas3(flat(X), T) / np.maximum(np.abs(_signed_area2(X, T)), 1e-16)
        out = tr.triangulate({"vertices": X, "triangles": T, "segments": out["segments"],
                              "triangle_max_area": a3 / np.maximum(J, 1.0)}, f"rpq{min_angle:g}aYQ")
    X, T = out["vertices"].copy(), out["triangles"].astype(np.int64)
    if not np.allclose(X[:n_out], loop):
        raise RuntimeError(f"panel {panel.name}: Triangle reordered the outline vertices")
    fixed = np.zeros(len(X), bool)
    fixed[:n_out] = True
    X = relax_panel(X, T, fixed, flat, relax_iters)
    return PanelMesh(X, T, fixed, keys, tags, seam_xz, flat)


def relax_panel(X, T, fixed, lift, iters: int, step: float = 0.6):
    """Centroidal smoothing in 3D, moved in pattern space (module doc, step 3)."""
    X = X.copy()
    n = len(X)
    free = ~fixed
    if not free.any():
        return X
    for _ in range(iters):
        P = lift(X)
        c = P[T].mean(1)
        A = _triangle_areas3(P, T)
        num = np.zeros((n, 3))
        den = np.zeros(n)
        for k in range(3):
            np.add.at(num, T[:, k], A[:, None] * c)
            np.add.at(den, T[:, k], A)
        # centroidal smoothing: the area-weighted mean of the incident triangles' centroids (the
        # discrete CVT update); it equalizes areas best, the mix with a plain neighbour average
        # that was tried gave max/min area ratios of 4-5 instead of 3-4
        target = num / np.maximum(den, 1e-30)[:, None]
        idx = np.nonzero(free)[0]
        Jm = lift.jacobian(X[idx])  # [m, 3, 2]
        d3 = target[idx] - P[idx]
        d2 = np.linalg.solve(np.einsum("nki,nkj->nij", Jm, Jm), np.einsum("nki,nk->ni", Jm, d3)[..., None])[..., 0]
        Xn = X.copy()
        Xn[idx] += step * d2
        # never fold a triangle in pattern space: revert moves around folded triangles
        for _ in range(10):
            bad = _signed_area2(Xn, T) <= 0
            if not bad.any():
                break
            vb = np.unique(T[bad])
            Xn[vb] = X[vb]
        X = Xn
    return X


@dataclass
class SewnMesh:
    vertices: np.ndarray  # [N, 3]
    faces: np.ndarray  # [F, 3]
    face_uvs: np.ndarray  # [F, 3, 2]
    face_panel: np.ndarray  # [F] panel index
    pattern_xz: np.ndarray  # [N, 2] flattened pattern coordinates (in the first panel holding the vertex)
    vertex_panel: np.ndarray  # [N]
    tags: dict  # tag -> [N] bool, outline vertices on pieces with that tag


def sew(panels: list[Panel], h: float, seam_lift, min_angle: float = 30.0) -> SewnMesh:
    """Mesh every panel, merge shared seam vertices, lay the UVs out side by side in [0, 1]²."""
    meshes = [mesh_panel(p, h, seam_lift, min_angle) for p in panels]
    verts, pat, vpan, faces, fpan, corner_xz = [], [], [], [], [], []
    key_to_id: dict = {}
    tags: dict = {}
    for pi, (panel, pm) in enumerate(zip(panels, meshes)):
        ids = np.empty(len(pm.xz), np.int64)
        P = pm.lift(pm.xz)
        for i in range(len(pm.xz)):
            key = pm.seam_key[i] if i < len(pm.seam_key) else None
            if key is not None and key in key_to_id:
                ids[i] = key_to_id[key]
                continue
            ids[i] = len(verts)
            # seam vertices lie on the seam curve itself (D = 0): both panels meet exactly
            verts.append(seam_lift(pm.seam_xz[i])[0] if key is not None else P[i])
            pat.append(pm.xz[i])
            vpan.append(pi)
            if key is not None:
                key_to_id[key] = ids[i]
        for i, t in enumerate(pm.tags):
            if t:
                tags.setdefault(t, set()).add(int(ids[i]))
        T = pm.tris[:, ::-1] if panel.flip else pm.tris
        faces.append(ids[T])
        fpan.append(np.full(len(T), pi))
        corner_xz.append(pm.xz[T])
    V = np.array(verts)
    F = np.concatenate(faces)
    fpan = np.concatenate(fpan)
    # UV layout: panels side by side (mirrored ones flipped in u), one uniform scale, 2% gaps
    cxz = corner_xz
    boxes = []
    for panel, c in zip(panels, cxz):
        u = -c[..., 0] if panel.mirror_uv else c[..., 0]
        boxes.append((u.min(), u.max(), c[..., 1].min(), c[..., 1].max()))
    gap = 0.02
    widths = [b[1] - b[0] for b in boxes]
    heights = [b[3] - b[2] for b in boxes]
    total = sum(widths)
    s = min((1.0 - gap * (len(panels) + 1)) / total, (1.0 - 2 * gap) / max(heights))
    uvs, u0 = [], gap
    for panel, c, b in zip(panels, cxz, boxes):
        u = -c[..., 0] if panel.mirror_uv else c[..., 0]
        uv = np.stack([u0 + s * (u - b[0]), gap + s * (c[..., 1] - b[2])], axis=-1)
        uvs.append(uv)
        u0 += s * (b[1] - b[0]) + gap
    tag_masks = {}
    for t, ids in tags.items():
        m = np.zeros(len(V), bool)
        m[list(ids)] = True
        tag_masks[t] = m
    return SewnMesh(V, F, np.concatenate(uvs), fpan, np.array(pat), np.array(vpan), tag_masks)
