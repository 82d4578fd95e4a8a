"""The projected texture: every texel's own surface point looked up in every training view that
sees it, shading divided out in closed form, unseen texels inpainted along the surface.

For a diffuse surface the image is linear in the albedo: a pixel that sees surface point x shows
I = T(x) · E(x), where E is the irradiance the lights give x (shadows and, with depth > 2, the
bounce included), i.e. the render of the same scene with a white texture. Over the views v that
see texel k (at its surface point x_k of that frame), the least-squares albedo is

    T_k = Σ_v w_v I_v(x_k) E_v(x_k) / Σ_v w_v E_v(x_k)²,       w_v = |cos θ_v| (foreshortening),

one division per texel instead of thousands of noisy gradient steps, and every texel is
estimated from all the views that see it, at its own position (not one colour per face).

- Visibility: a texel is seen by a view only when the camera ray towards its surface point hits
  the mesh at that point (Mitsuba ray casts against the frame's mesh): a texel hidden behind an
  arm or the garment does not take the occluder's colour.
- Pixels: inside the capture's foreground mask eroded by ``erode_px`` and inside the rendered
  silhouette (bilinear lookups never mix the background in), the image and E looked up
  bilinearly at the projected point.
- Unseen texels (the body under the garment, soles, a hem's underside): each face's colour is
  inpainted from its neighbours on the surface (harmonic interpolation over faces sharing an
  edge, so across UV chart seams and regardless of where the charts lie in the atlas), and every
  texel is pulled towards its face's colour with a weak prior (``prior_views`` views' worth), so
  barely seen texels do not keep one noisy observation; texels outside every UV triangle (chart
  padding) are dilated from the nearest texel (:func:`~.texture.fill_empty`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...camera import Camera
from ...render import MeshSpec, SceneSpec, load_scene, mitsuba
from .texture import fill_empty, texel_barycentrics


@dataclass
class TexelPoints:
    """The covered texels of an atlas: flat index ``rows * size + cols`` [N], face [N] and the
    barycentric weights [N, 3] of the texel centre in that face."""

    size: int
    index: np.ndarray
    face: np.ndarray
    bary: np.ndarray

    @staticmethod
    def of(face_uvs: np.ndarray, size: int) -> "TexelPoints":
        fmap, bary = texel_barycentrics(face_uvs, size)
        idx = np.flatnonzero(fmap.ravel() >= 0)
        return TexelPoints(int(size), idx, fmap.ravel()[idx], bary.reshape(-1, 3)[idx])

    def positions(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """[N, 3] surface points of the texels on the mesh ``vertices`` [V, 3]."""
        return np.einsum("nk,nkd->nd", self.bary, vertices[faces[self.face]])


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[F, 3] unit normals (counter-clockwise faces)."""
    v = vertices[faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)


class Occlusion:
    """Ray casts against one frame's mesh (all faces, as the renderer sees them)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.mi = mitsuba()
        self.scene = load_scene(SceneSpec(meshes=[MeshSpec("occ", vertices, faces, smooth=False)]))

    def visible(self, origin: np.ndarray, points: np.ndarray, rel_tol: float = 2e-4, abs_tol: float = 1e-4) -> np.ndarray:
        """[N] bool: the segment from ``origin`` to each of ``points`` [N, 3] (on the surface)
        reaches the point before it hits anything (within ``abs_tol + rel_tol · distance``)."""
        mi = self.mi
        d = np.asarray(points, np.float64) - np.asarray(origin, np.float64)
        dist = np.linalg.norm(d, axis=1)
        d = (d / np.maximum(dist, 1e-20)[:, None]).astype(np.float32)
        o = [np.full(len(d), float(x), np.float32) for x in origin]
        si = self.scene.ray_intersect(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2])))
        t = np.array(si.t, np.float64)
        hit = np.array(si.is_valid(), bool)
        return ~hit | (t >= dist - (abs_tol + rel_tol * dist))

    def depth(self, cam: Camera) -> np.ndarray:
        """[H, W] camera-space depth z of the surface seen through each pixel centre (inf:
        background)."""
        mi = self.mi
        o, d = cam.pixel_rays()
        d = d.reshape(-1, 3).astype(np.float32)
        ray = mi.Ray3f(mi.Point3f(*[np.full(len(d), float(x), np.float32) for x in o]),
                       mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        si = self.scene.ray_intersect(ray)
        t = np.array(si.t, np.float64)
        t[~np.array(si.is_valid(), bool)] = np.inf
        return (t * (d.astype(np.float64) @ cam.w2c[2, :3])).reshape(cam.height, cam.width)


def bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an [H, W] or [H, W, C] image at pixel coordinates ``xy`` [N, 2] (pixel
    centres at integers; points must lie inside [0, W-1] × [0, H-1])."""
    H, W = img.shape[:2]
    x = np.clip(xy[:, 0], 0, W - 1)
    y = np.clip(xy[:, 1], 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2)
    fx, fy = x - x0, y - y0
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    return ((img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx) * (1 - fy)
            + (img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)


def _depth_agrees(depth: np.ndarray, xy: np.ndarray, z: np.ndarray, tol: np.ndarray | float) -> np.ndarray:
    """[N] bool: the 2×2 pixels around each ``xy`` see a surface within ``tol`` of depth ``z``
    over their whole area (a pixel is the box average of its area, so its 3×3 neighbours'
    centres are checked too)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    finite = np.where(np.isfinite(depth), depth, 1e30)
    lo, hi = minimum_filter(finite, size=3, mode="nearest"), maximum_filter(finite, size=3, mode="nearest")
    H, W = depth.shape
    x0 = np.clip(np.floor(xy[:, 0]).astype(np.int64), 0, W - 2)
    y0 = np.clip(np.floor(xy[:, 1]).astype(np.int64), 0, H - 2)
    ok = np.ones(len(xy), bool)
    for dy in (0, 1):
        for dx in (0, 1):
            ok &= (hi[y0 + dy, x0 + dx] - z <= tol) & (z - lo[y0 + dy, x0 + dx] <= tol)
    return ok


@dataclass
class Projection:
    """Accumulated observations per covered texel: ``num`` = Σ w I E, ``den`` = Σ w E² [N, 3],
    ``weight`` = Σ w [N] and ``views`` [N] the number of views that saw each texel."""

    points: TexelPoints
    num: np.ndarray
    den: np.ndarray
    weight: np.ndarray
    views: np.ndarray

    @staticmethod
    def empty(points: TexelPoints) -> "Projection":
        n = len(points.index)
        return Projection(points, np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n), np.zeros(n, np.int64))

    def observe(self, cam: Camera, vertices: np.ndarray, faces: np.ndarray, mask: np.ndarray, *,
                occlusion: Occlusion | None = None, twosided: np.ndarray | None = None, min_cos: float = 0.1,
                edge_tol: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which texels view ``cam`` sees on the mesh ``vertices``, and where (the tests of
        :meth:`add_view`). Returns (idx [n] covered-texel indices, xy [n, 2] pixel positions,
        w [n] foreshortening weights |cos θ|)."""
        pts = self.points.positions(vertices, faces)
        xy, z = cam.project(pts)
        H, W = mask.shape[:2]
        ok = (z > 1e-6) & (xy[:, 0] >= 0) & (xy[:, 0] <= W - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= H - 1)
        n = face_normals(vertices, faces)[self.points.face]
        view = cam.center[None, :] - pts
        cos = np.einsum("nd,nd->n", n, view) / np.maximum(np.linalg.norm(view, axis=1), 1e-20)
        if twosided is not None:
            cos = np.where(np.asarray(twosided, bool)[self.points.face], np.abs(cos), cos)
        ok &= cos > min_cos
        idx = np.flatnonzero(ok)
        ok[idx] = bilinear(mask.astype(np.float32), xy[idx]) > 0.999
        idx = np.flatnonzero(ok)
        occ = occlusion if occlusion is not None else Occlusion(vertices, faces)
        ok[idx] = occ.visible(cam.center, pts[idx])
        idx = np.flatnonzero(ok)
        if edge_tol is not None and np.isfinite(edge_tol):
            slope = 2.0 * z[idx] / cam.K[0, 0] / np.maximum(cos[idx], 0.2)
            ok[idx] = _depth_agrees(occ.depth(cam), xy[idx], z[idx], edge_tol + slope)
            idx = np.flatnonzero(ok)
        return idx, xy[idx], cos[idx]

    def add_view(self, cam: Camera, vertices: np.ndarray, faces: np.ndarray, image: np.ndarray, mask: np.ndarray,
                 irradiance: np.ndarray, *, occlusion: Occlusion | None = None, twosided: np.ndarray | None = None,
                 min_cos: float = 0.1, edge_tol: float = 0.02) -> np.ndarray:
        """Add one view: ``image`` [H, W, 3] linear, ``mask`` [H, W] bool (pixels allowed),
        ``irradiance`` [H, W, 3] (the white-texture render, the silhouette's outside 0), on the
        mesh ``vertices``; ``twosided`` [F] bool faces seen from both sides (garments).
        A sample is dropped when one of the four pixels its bilinear lookup reads sees a surface
        at another depth than the texel's (an occlusion edge: the pixel mixes two surfaces, e.g.
        an arm's outline over the chest): more than ``edge_tol`` (m) plus the depth change that
        two pixels of the texel's own slope span.
        Returns the [N] bool texels this view saw."""
        idx, xy, cos = self.observe(cam, vertices, faces, mask, occlusion=occlusion, twosided=twosided,
                                    min_cos=min_cos, edge_tol=edge_tol)
        I = bilinear(image, xy)
        E = bilinear(irradiance, xy)
        w = cos[:, None]
        self.num[idx] += w * I * E
        self.den[idx] += w * E * E
        self.weight[idx] += w[:, 0]
        self.views[idx] += 1
        ok = np.zeros(len(self.points.index), bool)
        ok[idx] = True
        return ok


def face_adjacency(faces: np.ndarray):
    """Sparse [F, F] symmetric 0/1 matrix of faces that share an edge."""
    import scipy.sparse as sp

    F = len(faces)
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    fid = np.tile(np.arange(F), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, fid = e[order], fid[order]
    same = (e[1:] == e[:-1]).all(1)
    a, b = fid[:-1][same], fid[1:][same]
    A = sp.coo_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])), shape=(F, F)).tocsr()
    A.data[:] = 1.0
    return A


def inpaint_faces(faces: np.ndarray, values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """[F, C] ``values`` with the faces not ``known`` replaced by the harmonic interpolation of
    the known ones over the surface (each unknown face the mean of its edge neighbours); a
    component with no known face takes the mean of all known values."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    values = np.asarray(values, np.float64)
    known = np.asarray(known, bool)
    out = values.copy()
    if known.all() or not known.any():
        return out
    A = face_adjacency(faces)
    u, k = np.flatnonzero(~known), np.flatnonzero(known)
    L = sp.diags(np.asarray(A.sum(1)).ravel()) - A
    eps = 1e-6  # ties a component without known faces to the global mean
    mean = values[known].mean(0)
    lhs = (L[u][:, u] + eps * sp.eye(len(u))).tocsc()
    rhs = A[u][:, k] @ values[k] + eps * mean[None, :]
    sol = spsolve(lhs, rhs)
    out[u] = sol.reshape(len(u), -1)
    return out


def solve_texture(proj: Projection, faces: np.ndarray, *, prior_views: float = 0.5,
                  min_weight: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """The texture [size, size, 3] from the accumulated views (module docstring), and the [F]
    bool faces that some view saw (total foreshortening weight ≥ ``min_weight``).

    Each face's colour is the least-squares colour of all its texels' observations; unseen
    faces are inpainted from their neighbours; each texel is the least-squares value with its
    face's colour as a prior worth ``prior_views`` views of median irradiance."""
    pts = proj.points
    F = len(faces)
    fw = np.bincount(pts.face, weights=proj.weight, minlength=F)
    fnum = np.stack([np.bincount(pts.face, weights=proj.num[:, c], minlength=F) for c in range(3)], 1)
    fden = np.stack([np.bincount(pts.face, weights=proj.den[:, c], minlength=F) for c in range(3)], 1)
    seen = fw >= min_weight
    fcol = np.where(seen[:, None], fnum / np.maximum(fden, 1e-20), 0.0)
    fcol = inpaint_faces(faces, fcol, seen)
    # prior weight: prior_views views at the median E² of the observations
    e2 = proj.den[proj.weight > 0] / proj.weight[proj.weight > 0][:, None]
    lam = prior_views * (np.median(e2, 0) if len(e2) else np.ones(3))
    val = (proj.num + lam * fcol[pts.face]) / (proj.den + lam)
    size = pts.size
    tex = np.zeros((size * size, 3), np.float32)
    tex[pts.index] = val
    filled = np.zeros(size * size, bool)
    filled[pts.index] = True
    tex = fill_empty(tex.reshape(size, size, 3), filled.reshape(size, size))
    return np.clip(tex, 0.0, 1.0).astype(np.float32), seen
