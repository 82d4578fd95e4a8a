"""Refining the visual hull against the images and the fitted body.

A visual hull is the largest shape consistent with the silhouettes: it is right where a camera
sees the surface edge-on (the rims) and too large in every concavity (between an arm and the
hip, under the arms, between the legs under a skirt). Two kinds of evidence move it inward:

* **Photo-consistency** (multi-view stereo along the normal): for each hull vertex seen by at
  least two cameras at a useful angle, candidate positions along its normal (inward up to
  ``search_in``, outward ``search_out``) are scored by the mean pairwise normalised
  cross-correlation (NCC) of small patches of the tangent plane projected into those cameras;
  the best candidate counts where its score is high and clearly above the vertex's median
  score. This is the plane-sweep photo-consistency of multi-view stereo (e.g. Furukawa &
  Ponce's PMVS; Goesele et al.), restricted to the normal line because the hull is close.
  A depth that differs from the median of its neighbours' (two rings) by more than
  ``agree_px`` pixel footprints is a wrong peak and carries no evidence (:func:`agreeing`).
  The search reaches down to the fitted body under each vertex (plus ``body_slack``, at most
  ``search_max``) where that is deeper than ``search_in``: the surface lies between the hull and
  the body, and a hull can be several centimetres loose where an occluder keeps every camera
  from carving it (in front of the waist between the hands in the side views).
* **The height over the body** where a seen vertex has no evidence (:func:`_offset_prior`): the
  photo evidence's height above the body, spread over the mesh, bounds it; a hull vertex far
  above that is a hull tail and is drawn down to it.
* **The body prior** where no camera sees the surface: hull vertices that face away from every
  camera (the underside that closes the hull between a hem and the legs) are drawn to the
  fitted body's surface, which is the true surface under clothing there (as body-model priors
  fill unseen regions in ICON / ECON). Those facing down (``split_up``: the underside between a
  hem and the legs) are smoothed apart from the rest of the hull: a hem is an open edge, the
  cloth does not continue to the legs, and a field smoothed across it drags the seen hem up
  into the skirt by the centimetres the underside moves (docs/prepare.md, Session 36).

Both give each vertex a target and a confidence; a smooth displacement field (the mesh's graph
Laplacian as the regulariser, one sparse solve, scipy) spreads them to the vertices without
evidence, and the result never leaves the hull (a vertex that would leave any mask is moved
back).
"""

from __future__ import annotations

import numpy as np

from ...geometry.mesh import vertex_normals
from .config import RefineConfig
from .segment import visible


def _grey(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img, np.float32)
    if a.ndim == 3:
        a = a[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    return a / (255.0 if a.max() > 1.5 else 1.0)


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    h, w = img.shape
    u = np.clip(u, 0, w - 1.001)
    v = np.clip(v, 0, h - 1.001)
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    a, b = u - u0, v - v0
    return ((1 - a) * (1 - b) * img[v0, u0] + a * (1 - b) * img[v0, u0 + 1]
            + (1 - a) * b * img[v0 + 1, u0] + a * b * img[v0 + 1, u0 + 1])


def _tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.where(np.abs(n[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def view_cosines(V: np.ndarray, N: np.ndarray, cameras: list, spacing: float) -> np.ndarray:
    """[C, V] cosine between each vertex's normal and its ray to each camera where the camera
    sees it (facing and not hidden: a point z-buffer), else 0."""
    out = np.zeros((len(cameras), len(V)))
    for i, c in enumerate(cameras):
        vis, _ = visible(V, N, c, spacing)
        to_cam = c.center[None] - V
        cos = (N * to_cam).sum(1) / np.linalg.norm(to_cam, axis=1)
        out[i] = np.where(vis, np.clip(cos, 0.0, 1.0), 0.0)
    return out


def photo_depths(V: np.ndarray, N: np.ndarray, cameras: list, images: dict[str, np.ndarray], cfg: RefineConfig,
                 view_cos: np.ndarray, footprint: float,
                 reach: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(offset along -N [V] m, score [V], cameras used [V]) of the most photo-consistent position
    of each vertex on its normal line; score -1 where fewer than two cameras see it well
    (``view_cos`` [C, V] from :func:`view_cosines`). ``reach`` [V] (m): how far inward each
    vertex is searched (default ``cfg.search_in`` for all)."""
    nV, nC = len(V), len(cameras)
    cosw = np.where(view_cos > cfg.min_cos, view_cos, 0.0)
    # the best-facing cameras of each vertex
    k = min(cfg.cameras, nC)
    order = np.argsort(-cosw, axis=0)[:k]  # [k, V]
    wsel = np.take_along_axis(cosw, order, 0)  # [k, V]
    used = (wsel > 0).sum(0)
    reach = np.full(nV, cfg.search_in) if reach is None else np.asarray(reach, np.float64)
    offsets = np.arange(-cfg.search_out, float(reach.max(initial=cfg.search_in)) + 1e-9, cfg.step_px * footprint)
    h = cfg.patch_px * footprint
    g = np.arange(cfg.patch) - (cfg.patch - 1) / 2
    ga, gb = [x.ravel() * h for x in np.meshgrid(g, g, indexing="ij")]  # [P]
    t1, t2 = _tangents(N)
    greys = [_grey(images[c.name]) for c in cameras]
    best = np.zeros(nV)
    score = np.full(nV, -1.0)
    ok_v = np.flatnonzero(used >= 2)
    nO, P = len(offsets), len(ga)
    for s in range(0, len(ok_v), cfg.chunk):
        ids = ok_v[s:s + cfg.chunk]
        # [n, O, P, 3] patch points
        base = V[ids, None, :] - offsets[None, :, None] * N[ids, None, :]
        pts = base[:, :, None, :] + ga[None, None, :, None] * t1[ids, None, None] + gb[None, None, :, None] * t2[ids, None, None]
        samples = np.zeros((k, len(ids), nO, P), np.float32)
        for j in range(k):
            cam_of = order[j, ids]
            for ci in np.unique(cam_of[wsel[j, ids] > 0]):
                m = (cam_of == ci) & (wsel[j, ids] > 0)
                uv, _ = cameras[ci].project(pts[m].reshape(-1, 3))
                samples[j, m] = _bilinear(greys[ci], uv[:, 0], uv[:, 1]).reshape(-1, nO, P)
        x = samples - samples.mean(-1, keepdims=True)
        sd = np.sqrt((x ** 2).mean(-1, keepdims=True))
        textured = sd > cfg.min_contrast
        x = np.where(textured, x / np.maximum(sd, 1e-6), 0.0)
        w = (wsel[:, ids] > 0).astype(np.float32)[:, :, None] * textured[..., 0]  # [k, n, O]
        num = np.zeros((len(ids), nO), np.float32)
        den = np.zeros((len(ids), nO), np.float32)
        for a in range(k):
            for b in range(a + 1, k):
                ww = w[a] * w[b]
                num += ww * (x[a] * x[b]).mean(-1)
                den += ww
        within = offsets[None] <= reach[ids, None] + 1e-9  # [n, O]
        ncc = np.where((den > 0) & within, num / np.maximum(den, 1e-9), -1.0)
        j = np.argmax(ncc, 1)
        top = ncc[np.arange(len(ids)), j]
        med = np.nanmedian(np.where(within, ncc, np.nan), 1)
        good = (top >= cfg.min_score) & (top - med >= cfg.min_peak)
        best[ids] = np.where(good, offsets[j], 0.0)
        score[ids] = np.where(good, top, -1.0)
    return best, score, used


def _rings(F: np.ndarray, n: int, rings: int):
    """[n, n] sparse boolean: the vertices within ``rings`` edges of each vertex (itself left out)."""
    from scipy import sparse

    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    R = A.copy()
    for _ in range(rings - 1):
        R = ((R @ A + R) > 0).astype(np.float64)
    R.setdiag(0)
    R.eliminate_zeros()
    return R.tocsr()


def agreeing(F: np.ndarray, depth: np.ndarray, has: np.ndarray, rings: int, tol: float, min_neighbours: int = 3) -> np.ndarray:
    """[V] bool: the vertices with evidence (``has``) whose ``depth`` lies within ``tol`` of the
    median depth of their neighbours with evidence (within ``rings`` edges); a vertex with fewer
    than ``min_neighbours`` such neighbours keeps its evidence. A wrong NCC peak (a repeated
    pattern, a patch that straddles an occluding edge) is an isolated jump of a centimetre or
    more on a surface whose neighbours agree with each other: the robust test of depth-map
    filtering in multi-view stereo (a median over the neighbourhood)."""
    R = _rings(F, len(depth), rings)
    keep = has.copy()
    for i in np.flatnonzero(has):
        nb = R.indices[R.indptr[i]:R.indptr[i + 1]]
        nb = nb[has[nb]]
        if len(nb) >= min_neighbours and abs(depth[i] - np.median(depth[nb])) > tol:
            keep[i] = False
    return keep


def _laplacian(F: np.ndarray, n: int, apart: np.ndarray | None = None, held: np.ndarray | None = None):
    """[n, n] the mesh's graph Laplacian (unit edge weights); with ``apart`` and ``held`` [n]
    bool, the edges between a vertex in ``apart`` and a ``held`` one outside it are left out (the
    field is not smoothed across that border)."""
    from scipy import sparse

    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e = np.unique(np.sort(e, 1), axis=0)
    if apart is not None:
        a, b = apart[e[:, 0]], apart[e[:, 1]]
        e = e[~((a & ~b & held[e[:, 1]]) | (b & ~a & held[e[:, 0]]))]
    A = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    A = (A + A.T).tocsr()
    A.data[:] = 1.0
    return sparse.diags(np.asarray(A.sum(1)).ravel()) - A


def _spread(L, c: np.ndarray, rhs: np.ndarray, rings: float) -> np.ndarray:
    """``rhs`` [V, k] spread over the mesh from the vertices weighted ``c`` [V] by one screened
    Laplacian (decay length ``rings`` edges): a normalised convolution's numerator; with ``rhs``
    = ``c``, the indicator's spread (1 amid the vertices, falling away from them)."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    A = (sparse.diags(c) + L + sparse.identity(L.shape[0]) / rings ** 2).tocsc()
    return np.asarray(spsolve(A, rhs)).reshape(L.shape[0], -1)


def _offset_prior(V, L, body_q, on_body, target, conf, known, free, cfg: RefineConfig, fp: float, info: dict) -> None:
    """Where a seen vertex has no evidence of its own, the garment's height above the body that
    its neighbours' photo evidence gives (a smooth field over the mesh, one sparse solve) bounds it: a
    hull vertex higher above the body than that by more than ``offset_tol`` pixel footprints is
    a hull tail (a concavity no camera's silhouette carves, e.g. in front of the waist between the
    hands in the side views) and is drawn down to it with weight ``w_offset`` (in place of the
    hull anchor). Changes ``target`` and ``conf`` in place."""
    h_hull, bp, _ = on_body  # body_q.signed_distance(V), the caller's
    h_known = body_q.signed_distance(target[known])[0]
    c = np.zeros(len(V))
    c[known] = 1.0
    rhs = np.zeros(len(V))
    rhs[known] = h_known
    # normalised convolution on the mesh: the evidence's heights and its indicator spread by the
    # same screened Laplacian (decay length ``offset_rings`` edges); their ratio is the local
    # mean height, the indicator's spread (1 amid evidence, falling away from it) its support
    sol = _spread(L, c, np.stack([rhs, c], 1), cfg.offset_rings)
    support = sol[:, 1]
    h = sol[:, 0] / np.maximum(support, 1e-9)
    tail = free & (support >= cfg.offset_support) & (h_hull > h + cfg.offset_tol * fp) & (h > 0)
    up = V - bp
    up /= np.maximum(np.linalg.norm(up, axis=1, keepdims=True), 1e-12)
    target[tail] = bp[tail] + h[tail, None] * up[tail]
    conf[tail] = cfg.w_offset * support[tail]
    info["offset_prior"] = {"vertices": int(tail.sum()),
                            "moved_mean_mm": round(float(np.linalg.norm(target[tail] - V[tail], axis=1).mean() * 1000), 1)
                            if tail.any() else 0.0}


def refine_hull(V: np.ndarray, F: np.ndarray, cameras: list, images: dict[str, np.ndarray],
                masks: dict[str, np.ndarray], body_vertices: np.ndarray | None, body_faces: np.ndarray | None,
                cfg: RefineConfig) -> tuple[np.ndarray, dict]:
    """The hull's vertices moved by photo-consistency and the body prior (see the module doc);
    (vertices [V, 3], numbers for the report; ``_on_body`` [V] bool: the vertices drawn onto the body)."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    from .mesh import occupancy, pixel_footprint

    V = np.asarray(V, np.float64)
    N = vertex_normals(V, F)
    edge = float(np.median(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1)))
    fp = pixel_footprint(cameras, V.mean(0))
    target = V.copy()
    conf = np.zeros(len(V))
    info: dict = {"pixel_mm": round(fp * 1000, 2)}
    view_cos = view_cosines(V, N, cameras, 0.5 * edge)
    seen = (view_cos > cfg.unseen_cos).any(0)
    body_q, on_body, photo_has = None, None, np.zeros(len(V), bool)
    if body_vertices is not None:
        from ...geometry.closest import MeshQuery

        body_q = MeshQuery(body_vertices, body_faces, spacing=0.02)
        on_body = body_q.signed_distance(V)  # (height over the body, closest point, normal) of every vertex
    if cfg.photo and images:
        reach = None
        if body_q is not None and cfg.search_max > cfg.search_in:
            # the surface lies between the hull and the body under it: search down to the body
            db = np.abs(on_body[0])
            reach = np.clip(db + cfg.body_slack, cfg.search_in, cfg.search_max)
            info["search_reach_mm"] = {"median": round(float(np.median(reach)) * 1000, 1),
                                    "beyond_search_in": int((reach > cfg.search_in + 1e-9).sum())}
        d, s, used = photo_depths(V, N, cameras, images, cfg, view_cos, fp, reach)
        has = s > 0
        if cfg.agree_px > 0 and has.any():
            ok = agreeing(F, d, has, cfg.agree_rings, cfg.agree_px * fp)
            info["photo_disagreeing"] = int((has & ~ok).sum())
            has = ok
        d = np.clip(d, 0.0, None)  # the hull contains the surface: inward only
        target[has] = V[has] - d[has, None] * N[has]
        conf[has] = cfg.w_photo * s[has]
        photo_has = has
        info["_photo"] = np.where(used >= 2, has.astype(np.float64), np.nan)
        info["photo"] = {"vertices_with_evidence": int(has.sum()), "seen_by_two": int((used >= 2).sum()),
                         "moved_mean_mm": round(float(d[has].mean() * 1000), 2) if has.any() else 0.0}
    unseen = np.zeros(len(V), bool)
    if cfg.body_prior and body_q is not None:
        unseen = ~seen & (conf == 0)
        info["_on_body"] = unseen
        if unseen.any():
            qp, qn = on_body[1][unseen], on_body[2][unseen]
            tgt = qp + cfg.body_margin * qn
            target[unseen] = tgt
            conf[unseen] = cfg.w_body
            info["body_prior"] = {"unseen_vertices": int(unseen.sum()),
                                  "moved_mean_mm": round(float(np.linalg.norm(tgt - V[unseen], axis=1).mean() * 1000), 1)}
    L = _laplacian(F, len(V))
    split, held = np.zeros(len(V), bool), None
    if cfg.split_up > -1.5 and unseen.any() and photo_has.any():
        # the unseen underside apart from the seen vertices amid photo evidence (the evidence's
        # spread, as the height prior's support): where none is near (coarse pixels), the body
        # prior's pull on its seen neighbours is the best guess there is, and stays
        split = unseen & (N[:, 2] <= cfg.split_up)
        held = seen & (_spread(L, photo_has.astype(np.float64), photo_has.astype(np.float64),
                               cfg.offset_rings)[:, 0] >= cfg.offset_support)
        info["split_from_seen"] = int(split.sum())
    if cfg.w_offset > 0 and body_q is not None and photo_has.any():
        _offset_prior(V, L, body_q, on_body, target, conf, photo_has, seen & (conf == 0), cfg, fp, info)
    # the hull itself, weakly, where a camera sees it and nothing else speaks
    hull_anchor = (conf == 0) & seen
    conf[hull_anchor] = cfg.w_hull
    if not (conf > 0).any():
        return V, info | {"moved": 0}
    Ls = _laplacian(F, len(V), split, held) if split.any() else L
    A = (sparse.diags(conf) + cfg.smoothness * Ls).tocsc()
    A = A + sparse.identity(len(V)) * 1e-6
    disp = spsolve(A, conf[:, None] * (target - V))
    disp = np.asarray(disp).reshape(len(V), 3)
    out = V + disp
    # never outside the hull: halve the displacement of vertices that leave any mask
    occ0 = occupancy(V, cameras, masks, 1.0)
    for _ in range(4):
        occ = occupancy(out, cameras, masks, 1.0)
        bad = occ < np.minimum(occ0, 0.5) - 0.05
        if not bad.any():
            break
        disp[bad] *= 0.5
        out = V + disp
    moved = np.linalg.norm(disp, axis=1)
    info["moved"] = int((moved > 0.5 * fp).sum())
    info["moved_mean_mm"] = round(float(moved.mean() * 1000), 2)
    info["moved_max_mm"] = round(float(moved.max() * 1000), 1)
    return out, info
