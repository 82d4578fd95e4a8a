"""Procedural garments for the foreign captures: a flared skirt and a fitted top, built around a
body's rest pose by the benchmark itself (not physavatar's pattern-based designs).

Each garment is a ruled surface of rings around the body's vertical axis: a ring's radius at
angle φ is the body's outer radius in that direction over the garment's span so far (the torso,
arms excluded; the two legs together below the crotch), plus a clearance, plus, for the skirt, a
flare that grows linearly with the distance below the waist. The top ring is pinned to the body
(waistband / neckline); the simulator then drapes the garment.

Also: attaching points to a body surface (barycentric coordinates on the closest triangle plus
an offset along its normal) so pinned vertices follow the posed body.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree


@dataclasses.dataclass
class ProceduralGarment:
    name: str
    vertices: np.ndarray  # [N, 3]
    faces: np.ndarray  # [F, 3], outward
    pinned: np.ndarray  # [K] vertex ids that stay on the body


def body_radius(tris: np.ndarray, z: float, phis: np.ndarray, center) -> np.ndarray:
    """The body's outer radius [len(phis)] around ``center`` (x, y) at height z per direction φ:
    the farthest crossing of the horizontal half-line from the axis along φ with the body's
    triangles ``tris`` [F, 3, 3] (Möller–Trumbore), NaN where it crosses none."""
    d = np.stack([np.cos(phis), np.sin(phis), np.zeros_like(phis)], 1)  # [R, 3]
    o = np.array([center[0], center[1], z])
    a, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    p = np.cross(d[:, None], e2[None])  # [R, F, 3]
    det = np.einsum("rfk,fk->rf", p, e1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o[None] - a  # [F, 3]
    u = np.einsum("rfk,fk->rf", p, s) * inv
    q = np.cross(s, e1)  # [F, 3]
    v = np.einsum("rk,fk->rf", d, q) * inv
    t = np.einsum("fk,fk->f", q, e2)[None] * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = np.where(hit, t, np.nan)
    with np.errstate(all="ignore"):
        return np.nanmax(np.where(hit, t, -np.inf), axis=1).clip(min=0) * np.where(hit.any(1), 1.0, np.nan)


def _fill_periodic(r: np.ndarray) -> np.ndarray:
    if np.isnan(r).all():
        return r
    n = len(r)
    i = np.arange(n)
    ok = ~np.isnan(r)
    return np.interp(i, np.r_[i[ok] - n, i[ok], i[ok] + n], np.r_[r[ok], r[ok], r[ok]])


def _ring_mesh(rings: list[np.ndarray]) -> np.ndarray:
    """Faces joining consecutive closed rings of equal size (ring 0 at the top), outward normals."""
    n = len(rings[0])
    F = []
    for r in range(len(rings) - 1):
        for j in range(n):
            a, b = r * n + j, r * n + (j + 1) % n
            c, d = a + n, b + n
            # alternate the diagonal for a more isotropic mesh
            if (r + j) % 2:
                F += [[a, c, b], [b, c, d]]
            else:
                F += [[a, c, d], [a, d, b]]
    return np.asarray(F, np.int64)


def _garment(name, body, keep, center, z_top, length, clearance, flare_deg, edge, pin_rows=1):
    V, BF = body.rest_vertices, body.faces
    mesh = V[BF[keep[BF].all(1)]]  # the body's triangles, arms left out
    # columns: the hem's edges (the widest ring) are at most 1.2 edge long
    r_max = 0.2 + length * np.tan(np.radians(flare_deg))
    n_ang = max(24, round(2 * np.pi * r_max / (1.2 * edge)))
    phis = np.linspace(-np.pi, np.pi, n_ang, endpoint=False)
    rows = max(3, round(length / edge) + 1)
    zs = np.linspace(z_top, z_top - length, rows)
    rings, r_prev = [], None
    for z in zs:
        # the outer radius over a slab around z (rays at 3 heights), widest so far below the top
        r = np.fmax.reduce([body_radius(mesh, z + dz, phis, center) for dz in (-0.012, 0.0, 0.012)])
        r = _fill_periodic(r)
        if np.isnan(r).all():
            r = r_prev
        r = np.convolve(np.r_[r[-1], r, r[0]], [0.25, 0.5, 0.25], "valid") * 0.5 + 0.5 * r
        if r_prev is not None and flare_deg > 0:
            r = np.maximum(r, r_prev)  # a skirt hangs straight over the hips and legs
        r_prev = r
        r_out = r + clearance + (z_top - z) * np.tan(np.radians(flare_deg))
        rings.append(np.stack([center[0] + r_out * np.cos(phis), center[1] + r_out * np.sin(phis),
                               np.full(n_ang, z)], 1))
    P = np.concatenate(rings)
    F = _ring_mesh(rings)
    return ProceduralGarment(name, P, F, np.arange(pin_rows * n_ang))


def arm_mask(body) -> np.ndarray:
    """Body vertices skinned mostly to arm bones (excluded from torso cross-sections)."""
    W = body.skinning_weights
    names = body.bone_names
    arm = np.array([any(k in n for k in ("clavicle", "shoulder", "arm", "wrist", "finger", "metacarpal", "thumb"))
                    for n in names])
    return W[:, arm].sum(1) > 0.3


def flared_skirt(body, edge: float = 0.025, length: float = 0.5, flare_deg: float = 22.0,
                 clearance: float = 0.012) -> ProceduralGarment:
    V = body.rest_vertices
    H = V[:, 2].max()
    keep = ~arm_mask(body)
    center = V[keep & (np.abs(V[:, 2] - 0.58 * H) < 0.05), :2].mean(0)
    return _garment("flared-skirt", body, keep, center, 0.60 * H, length, clearance, flare_deg, edge)


def fitted_top(body, edge: float = 0.025, clearance: float = 0.008) -> ProceduralGarment:
    V = body.rest_vertices
    H = V[:, 2].max()
    keep = ~arm_mask(body)
    center = V[keep & (np.abs(V[:, 2] - 0.68 * H) < 0.05), :2].mean(0)
    z_top = 0.73 * H
    return _garment("fitted-top", body, keep, center, z_top, z_top - 0.53 * H, clearance, 0.0, edge)


# -- attachment ------------------------------------------------------------------------------------

@dataclasses.dataclass
class Attach:
    face: np.ndarray  # [K]
    bary: np.ndarray  # [K, 3]
    offset: np.ndarray  # [K] along the face normal


def attach(points: np.ndarray, BV: np.ndarray, BF: np.ndarray, candidates: int = 16) -> Attach:
    """Each point's closest body triangle (among the nearest centroids), barycentric coordinates
    of its projection (clamped into the triangle) and its height along the normal."""
    cent = BV[BF].mean(1)
    _, cand = cKDTree(cent).query(points, k=candidates)
    best = np.zeros(len(points), np.int64)
    bary = np.zeros((len(points), 3))
    off = np.zeros(len(points))
    for i, p in enumerate(points):
        dbest = np.inf
        for f in cand[i]:
            a, b, c = BV[BF[f]]
            n = np.cross(b - a, c - a)
            n /= np.linalg.norm(n)
            h = (p - a) @ n
            q = p - h * n
            T = np.stack([b - a, c - a], 1)
            uv = np.linalg.lstsq(T, q - a, rcond=None)[0]
            w = np.clip(np.r_[1 - uv.sum(), uv], 0, None)
            w /= w.sum()
            d = np.linalg.norm(p - w @ np.stack([a, b, c]))
            if d < dbest:
                dbest, best[i], bary[i], off[i] = d, f, w, h
    return Attach(best, bary, off)


def attached_positions(att: Attach, BV_seq: np.ndarray, BF: np.ndarray) -> np.ndarray:
    """[T, K, 3] positions of attached points on a body sequence [T, Nb, 3]."""
    tri = BV_seq[:, BF[att.face]]  # [T, K, 3, 3]
    n = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.einsum("tkij,ki->tkj", tri, att.bary) + att.offset[None, :, None] * n
