"""Garment segmentation of the first-frame mesh, and the garments cut out as separate pieces.

Automatic labels (:func:`segment`), per vertex:

* **distance** to the fitted body (signed, negative inside): a vertex farther than ``margin``
  outside the body is garment, with a logistic transition ``softness`` wide;
* **colour** from the first frame's images: each vertex's median colour over the cameras that
  see it (normal towards the camera and not behind another surface point: a point z-buffer);
  a Gaussian per class, learned from the vertices the distance already decides, gives each
  vertex a colour log-likelihood ratio;
* **bridges**: vertices no camera sees that face down (the hull closing the gap between a hem
  and the legs) are split between the garment and the body by which is nearer;
* **photo-consistency** (evidence.py): where the hull refinement found a textured surface the
  cameras agree on; a patterned garment has it, bare skin under a hull's bridge has not. It may
  trim the garment the other terms give, not change its topology;
* a **graph cut** on the mesh (scipy's maximum flow): the two terms as unary costs, and a
  smoothness cost on every mesh edge, lower between vertices of different colours, so the
  cut follows the garment's edge.

Several garments (``garments`` > 1) are told apart by colour: k-means on the garment
vertices' colours, then a majority vote over mesh neighbours. Small pieces are given to their
surroundings. A user's labels (``--labels``) are transferred by nearest point instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import PhysavatarError
from ...geometry.mesh import adjacency, mesh_edges, vertex_normals
from ...labels import LABEL_BODY, MAX_LABEL
from .config import SegmentConfig
from .evidence import keep_topology, photo_term

SCALE = 1000  # capacities are integers for scipy's maximum flow


# -- colour ---------------------------------------------------------------------------------------

def visible(points: np.ndarray, normals: np.ndarray, cam, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """([n] bool, [n, 2] pixel positions): points facing ``cam`` and not behind another point
    (a z-buffer of the points splatted ``spacing`` wide)."""
    uv, z = cam.project(points)
    uv = np.nan_to_num(uv)
    to_cam = cam.center[None] - points
    facing = (normals * to_cam).sum(1) > 0.1 * np.linalg.norm(to_cam, axis=1)
    inside = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
    ok = facing & inside
    r = max(1, int(np.ceil(cam.K[0, 0] * spacing / np.median(z[ok]) if ok.any() else 1)))
    zbuf = np.full((cam.height, cam.width), np.inf)
    px = np.round(uv[ok]).astype(np.int64)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            x = np.clip(px[:, 0] + dx, 0, cam.width - 1)
            y = np.clip(px[:, 1] + dy, 0, cam.height - 1)
            np.minimum.at(zbuf, (y, x), z[ok])
    vis = np.zeros(len(points), bool)
    vis[ok] = z[ok] <= zbuf[px[:, 1], px[:, 0]] + 2.0 * spacing
    return vis, uv


def _samples(cameras: list, images: dict[str, np.ndarray], n: int, usable) -> np.ndarray:
    """[C, n, 3] each camera's pixel colour at the points it can use (NaN elsewhere);
    ``usable(camera)`` gives ([n] which points, [n, 2] their pixel positions)."""
    samples = np.full((len(cameras), n, 3), np.nan)
    for i, c in enumerate(cameras):
        ok, uv = usable(c)
        x = np.clip(np.round(uv[ok, 0]).astype(int), 0, c.width - 1)
        y = np.clip(np.round(uv[ok, 1]).astype(int), 0, c.height - 1)
        samples[i, ok] = images[c.name][y, x]
    return samples


def vertex_colours(vertices: np.ndarray, faces: np.ndarray, cameras: list, images: dict[str, np.ndarray],
                   spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """([V, 3] median colour over the cameras that see each vertex, [V] how many do)."""
    N = vertex_normals(vertices, faces)
    samples = _samples(cameras, images, len(vertices), lambda c: visible(vertices, N, c, spacing))
    seen = np.isfinite(samples[..., 0]).sum(0)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            col = np.nanmedian(samples, axis=0)
    return np.nan_to_num(col, nan=0.5), seen


def under_disagreement(points: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray, cameras: list,
                       images: dict[str, np.ndarray], min_cos: float = 0.5, occluders: np.ndarray | None = None,
                       spacing: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """([n] how much the cameras facing the fitted body's surface point under each point disagree on
    its colour: the median distance of their colours to the median colour; [n] how many).

    Where nothing lies between a point and the body (bare skin the visual hull bridges: between
    a dress's straps), the cameras see that body point itself and agree, even on plain skin; under
    a garment they see different parts of the cloth in front of it and disagree. The consistency
    test of voxel colouring (Seitz and Dyer), made at the body's surface instead of the hull's.

    ``occluders`` ([n] bool, the points taken for garment so far): a camera is not used for a
    body point when one of those points farther than ``2 h + 2 spacing`` from the point above it
    (``h`` its height above the body: its own patch, through which any camera sees the body) lies
    in front of the body point in that camera (a point z-buffer of the occluders, splatted
    ``spacing`` wide). Over bare skin between a dress's straps, an oblique camera sees a strap in
    front of the skin: it saw the strap, not the skin, and made the skin look covered."""
    from ...geometry.closest import MeshQuery

    _, f, w, P = MeshQuery(body_vertices, body_faces, spacing=0.02).closest(points)
    BN = vertex_normals(body_vertices, body_faces)
    N = (BN[body_faces[f]] * w[:, :, None]).sum(1)
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)

    def facing(c):
        uv, z = c.project(P)
        to = c.center[None] - P
        to /= np.maximum(np.linalg.norm(to, axis=1, keepdims=True), 1e-12)
        ok = ((N * to).sum(1) > min_cos) & (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) \
            & (uv[:, 0] <= c.width - 1) & (uv[:, 1] <= c.height - 1)
        if occluders is not None and occluders.any() and ok.any():
            ok &= ~_occluded(c, points, P, uv, z, ok, occluders, spacing)
        return ok, uv

    S = _samples(cameras, images, len(P), facing)
    n = np.isfinite(S[..., 0]).sum(0)
    dev = np.full(len(P), np.nan)
    m = n >= 2
    med = np.nanmedian(S[:, m], 0)
    dev[m] = np.nanmedian(np.linalg.norm(S[:, m] - med[None], axis=2), 0)
    return dev, n


def _occluded(cam, points: np.ndarray, P: np.ndarray, uv: np.ndarray, z: np.ndarray, ok: np.ndarray,
              occluders: np.ndarray, spacing: float) -> np.ndarray:
    """[n] bool: body point ``P[i]`` (at pixel ``uv[i]``, depth ``z[i]``; only where ``ok``) has an
    occluder point in front of it in ``cam`` that is farther than ``2 h + 2 spacing`` from
    ``points[i]`` (``h = |points[i] - P[i]|``)."""
    ids = np.flatnonzero(occluders)
    ouv, oz = cam.project(points[ids])
    good = (oz > 1e-6) & np.isfinite(ouv).all(1)
    ids, ouv, oz = ids[good], ouv[good], oz[good]
    out = np.zeros(len(P), bool)
    if not len(ids):
        return out
    r = max(1, int(np.ceil(cam.K[0, 0] * spacing / np.median(oz))))
    zbuf = np.full((cam.height, cam.width), np.inf)
    who = np.full((cam.height, cam.width), -1, np.int64)
    px = np.round(ouv).astype(np.int64)
    order = np.argsort(-oz)  # nearest written last: it wins
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            x, y = px[order, 0] + dx, px[order, 1] + dy
            inside = (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
            x, y, o = x[inside], y[inside], order[inside]
            nearer = oz[o] < zbuf[y, x]
            zbuf[y[nearer], x[nearer]] = oz[o[nearer]]
            who[y[nearer], x[nearer]] = ids[o[nearer]]
    q = np.flatnonzero(ok)
    x = np.clip(np.round(uv[q, 0]).astype(int), 0, cam.width - 1)
    y = np.clip(np.round(uv[q, 1]).astype(int), 0, cam.height - 1)
    occ = who[y, x]
    front = (occ >= 0) & (zbuf[y, x] < z[q] - 0.5 * spacing)
    h = np.linalg.norm(points[q] - P[q], axis=1)
    far = np.linalg.norm(points[np.maximum(occ, 0)] - points[q], axis=1) > 2 * h + 2 * spacing
    out[q] = front & far
    return out


def _mixture_loglik(x: np.ndarray, sel: np.ndarray, k: int = 3) -> np.ndarray:
    """[n] log-likelihood of ``x`` under a mixture of ``k`` Gaussians fitted to ``x[sel]`` (k-means
    clusters, each its own Gaussian, weighted by its size): a patterned garment has several colours."""
    import cv2

    data = x[sel].astype(np.float32)
    k = max(1, min(k, len(data) // 20))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-4)
    cv2.setRNGSeed(0)
    _, lab, _ = cv2.kmeans(data, k, None, crit, 3, cv2.KMEANS_PP_CENTERS)
    lab = lab.ravel()
    terms = []
    for j in range(k):
        m = data[lab == j]
        if len(m) < 4:
            continue
        mu = m.mean(0)
        cov = np.cov(m.T) + np.eye(x.shape[1]) * 1e-3
        inv = np.linalg.inv(cov)
        d = x - mu
        terms.append(np.log(len(m) / len(data)) - 0.5 * np.einsum("ni,ij,nj->n", d, inv, d)
                     - 0.5 * np.log(np.linalg.det(cov)))
    T = np.stack(terms)
    top = T.max(0)
    return top + np.log(np.exp(T - top).sum(0))


# -- graph cut ------------------------------------------------------------------------------------

def graph_cut(cost_fg: np.ndarray, cost_bg: np.ndarray, edges: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """[V] bool, True = foreground (garment): the labelling of least total unary cost
    (``cost_fg`` where labelled foreground, ``cost_bg`` where not) plus ``weights`` of the edges
    cut, by a minimum s-t cut (scipy.sparse.csgraph.maximum_flow)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    n = len(cost_fg)
    s, t = n, n + 1
    shift = np.minimum(cost_fg, cost_bg)
    cap_s = np.round((cost_bg - shift) * SCALE).astype(np.int64)  # cut when labelled background
    cap_t = np.round((cost_fg - shift) * SCALE).astype(np.int64)  # cut when labelled foreground
    w = np.round(weights * SCALE).astype(np.int64)
    rows = np.concatenate([np.full(n, s), np.arange(n), edges[:, 0], edges[:, 1]])
    cols = np.concatenate([np.arange(n), np.full(n, t), edges[:, 1], edges[:, 0]])
    caps = np.concatenate([cap_s, cap_t, w, w]).astype(np.int32)
    keep = caps > 0
    G = coo_matrix((caps[keep], (rows[keep], cols[keep])), shape=(n + 2, n + 2)).tocsr()
    G.sum_duplicates()
    flow = maximum_flow(G, s, t).flow
    residual = (G - flow).tocsr()
    residual.data = np.where(residual.data > 0, 1, 0).astype(np.int32)
    residual.eliminate_zeros()
    reach = breadth_first_order(residual, s, directed=True, return_predecessors=False)
    fg = np.zeros(n + 2, bool)
    fg[reach] = True
    return fg[:n]


# -- labelling ------------------------------------------------------------------------------------

def segment(vertices: np.ndarray, faces: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray,
            cameras: list, images: dict[str, np.ndarray], cfg: SegmentConfig, spacing: float,
            colour_vertices: np.ndarray | None = None, photo: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """[V] labels (0 body, 1.. garment) of the first-frame mesh, and the numbers behind them.
    ``colour_vertices``: the same vertices where the images are sampled (a refined surface's),
    when not ``vertices``; ``photo`` [V]: the refinement's photo-consistency evidence (1 found, 0
    not, NaN: seen by fewer than two cameras; evidence.photo_term), when it ran."""
    from ...geometry.closest import MeshQuery

    sd, _, _ = MeshQuery(body_vertices, body_faces, spacing=0.02).signed_distance(vertices)
    z = np.clip((sd - cfg.margin) / cfg.softness, -30, 30)
    # log p(garment) / p(body) from the distance, capped: near the body (a strap, a tight top) or
    # where the hull bulges out between limbs, the colour must be able to overrule it
    logit = np.clip(z, -cfg.distance_cap, cfg.distance_cap)
    colour, seen = vertex_colours(vertices if colour_vertices is None else colour_vertices, faces, cameras, images,
                                  spacing)
    g_seed, b_seed = (z > 2) & (seen > 0), (z < -2) & (seen > 0)
    info = {"distance_garment": int((z > 0).sum()), "colour_used": False}
    if cfg.colour_weight > 0 and g_seed.sum() >= 20 and b_seed.sum() >= 20:
        base = logit
        for _ in range(2):  # the colour models from the distance's seeds, then from their own result
            llr = np.clip(_mixture_loglik(colour, g_seed) - _mixture_loglik(colour, b_seed), -6, 6)
            logit = base + cfg.colour_weight * np.where(seen > 0, llr, 0.0)
            g_seed, b_seed = (logit > 2) & (seen > 0), (logit < -2) & (seen > 0)
            if g_seed.sum() < 20 or b_seed.sum() < 20:
                break
        info["colour_used"] = True
        if cfg.under_weight > 0:
            # the body under each vertex seen alike by its cameras: bare skin the hull bridges
            # cameras that see another part of the garment in front of the body point are left out
            occ = (logit > 0) if cfg.under_occlusion else None
            dev, _ = under_disagreement(vertices, body_vertices, body_faces, cameras, images, occluders=occ,
                                        spacing=spacing)
            ok = np.isfinite(dev)
            x = np.log(np.where(ok, dev, 1.0) + 0.005)[:, None]
            gs, bs = g_seed & ok & (sd > cfg.margin), b_seed & ok
            if gs.sum() >= 20 and bs.sum() >= 20:
                llr_u = np.clip(_mixture_loglik(x, gs, k=1) - _mixture_loglik(x, bs, k=1), -cfg.under_cap, cfg.under_cap)
                # only above the body: on it the body point is the vertex itself (colour decides)
                logit = logit + cfg.under_weight * np.where(ok & (sd > cfg.margin), llr_u, 0.0)
                info["under_body_votes"] = int(((llr_u < 0) & ok & (sd > cfg.margin)).sum())
    N = vertex_normals(vertices, faces)
    # unseen and facing down: the hull closing a gap no camera looks into (a hem to the legs)
    bridge = (seen == 0) & (N[:, 2] < cfg.bridge_normal)
    info["bridge"] = int(bridge.sum())
    E = mesh_edges(faces)
    dc = np.linalg.norm(colour[E[:, 0]] - colour[E[:, 1]], axis=1)
    sigma = max(float(np.median(dc)), 1e-3)
    w = cfg.smoothness * np.exp(-(dc / (2 * sigma)) ** 2)

    def cut(logit):
        p = 1 / (1 + np.exp(-np.clip(np.where(bridge, -cfg.distance_cap, logit), -30, 30)))
        cost_g, cost_b = -np.log(np.maximum(p, 1e-6)), -np.log(np.maximum(1 - p, 1e-6))
        return graph_cut(cost_g, cost_b, E, w) if cfg.smoothness > 0 else p > 0.5

    if photo is not None and cfg.photo_weight > 0:
        logit_p, info["photo"] = photo_term(logit, photo, faces, cfg)
        before = cut(logit)
        garment, info["photo"]["kept_for_topology"] = keep_topology(before, cut(logit_p), faces, np.argsort(logit_p))
        logit = logit_p
    else:
        garment = cut(logit)
    if bridge.any() and (garment & ~bridge).any():
        # a bridge is split where it is nearer the seen garment than the body
        from scipy.spatial import cKDTree

        dg, _ = cKDTree(vertices[garment & ~bridge]).query(vertices[bridge])
        garment[bridge] = dg < np.abs(sd[bridge])
    labels = np.where(garment, 1, LABEL_BODY).astype(np.int64)
    labels = _drop_small(labels, faces, len(vertices), cfg.min_piece)
    if cfg.garments > 1 and (labels > 0).sum() >= cfg.garments:
        labels = _split_by_colour(labels, colour, faces, cfg.garments)
    info["garment_vertices"] = int((labels > 0).sum())
    # the unary evidence (log-odds garment : body per vertex, before the cut's smoothing): the
    # strap joins (gaps.py) follow it where the cut left a strap body
    return labels, info | {"signed_distance": sd, "colour": colour, "bridge_mask": bridge, "logit": logit}


def _components(mask: np.ndarray, faces: np.ndarray, n: int):
    from scipy.sparse.csgraph import connected_components

    A = adjacency(faces, n)
    sub = A[mask][:, mask]
    k, lab = connected_components(sub, directed=False)
    return k, lab


def _drop_small(labels: np.ndarray, faces: np.ndarray, n: int, share: float) -> np.ndarray:
    """Garment pieces and body islands smaller than ``share`` of the garment given to their
    surroundings."""
    out = labels.copy()
    total = max(int((labels > 0).sum()), 1)
    for value, other in ((1, LABEL_BODY), (LABEL_BODY, 1)):
        mask = (out > 0) if value else (out == LABEL_BODY)
        if not mask.any():
            continue
        k, lab = _components(mask, faces, n)
        sizes = np.bincount(lab, minlength=k)
        idx = np.flatnonzero(mask)
        if value:
            small = sizes < share * total
            if small.all():
                small[np.argmax(sizes)] = False
        else:
            small = (sizes < share * total) & (sizes < sizes.max())
        out[idx[small[lab]]] = other
    return out


def _split_by_colour(labels: np.ndarray, colour: np.ndarray, faces: np.ndarray, k: int) -> np.ndarray:
    import cv2

    g = np.flatnonzero(labels > 0)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-4)
    cv2.setRNGSeed(0)
    _, lab, centres = cv2.kmeans(colour[g].astype(np.float32), k, None, crit, 4, cv2.KMEANS_PP_CENTERS)
    order = np.argsort(-centres[:, 1])  # stable numbering: by the centres' brightness
    rank = np.empty(k, np.int64)
    rank[order] = np.arange(k)
    out = labels.copy()
    out[g] = rank[lab.ravel()] + 1
    A = adjacency(faces, len(labels)).tocsr()
    for _ in range(5):  # majority of the neighbours (garment ones)
        onehot = np.zeros((len(labels), k + 1))
        onehot[np.arange(len(labels)), out] = 1
        votes = A @ onehot + onehot
        votes[:, 0] = -1
        new = np.where(out > 0, votes.argmax(1), 0)
        if (new == out).all():
            break
        out = new
    return out


def transfer_labels(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray | None, values: np.ndarray) -> np.ndarray:
    """Per-point values of the nearest vertex of another mesh's ``vertices`` (the nearest
    triangle's nearest corner when ``faces`` are given)."""
    if faces is not None and len(faces):
        from ...geometry.closest import MeshQuery

        _, f, w, _ = MeshQuery(vertices, faces, spacing=0.02).closest(points)
        corner = faces[f, np.argmax(w, axis=1)]
        return np.asarray(values)[corner]
    from scipy.spatial import cKDTree

    _, i = cKDTree(vertices).query(points)
    return np.asarray(values)[i]


def user_labels(path: Path, vertices: np.ndarray, source: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """Labels from a user's file (see ``--labels``) for the mesh ``vertices``; ``source`` is the
    capture's own mesh (vertices, faces) a .npy/.txt file numbers."""
    from ...files import read_ply

    path = Path(path)
    if not path.is_file():
        raise PhysavatarError(path, "labels file not found")
    if path.suffix.lower() == ".ply":
        ply = read_ply(path)
        if "label" not in ply.vertex_data:
            raise PhysavatarError(path, "PLY has no per-vertex 'label' property")
        lab = np.asarray(ply.vertex_data["label"]).astype(np.int64)
        src_v, src_f = ply.vertices, ply.faces
    else:
        try:
            lab = np.load(path) if path.suffix.lower() == ".npy" else np.loadtxt(path)
        except Exception as e:  # noqa: BLE001 - any parse failure is the file's problem
            raise PhysavatarError(path, f"unreadable labels ({type(e).__name__})") from None
        lab = np.asarray(lab).astype(np.int64).ravel()
        if source is None:
            raise PhysavatarError(path, "a .npy/.txt labels file numbers the capture's own mesh (meshes/<first "
                                  "frame>.ply), which this capture lacks: give a PLY with a 'label' property")
        if len(lab) != len(source[0]):
            raise PhysavatarError(path, f"has {len(lab)} labels but the capture's mesh has {len(source[0])} vertices")
        src_v, src_f = source
    if lab.min() < 0 or lab.max() > MAX_LABEL:
        raise PhysavatarError(path, f"labels must be 0 (body) .. {MAX_LABEL}, found {lab.min()}..{lab.max()}")
    if not (lab > 0).any():
        raise PhysavatarError(path, "no garment vertices (every label is 0)")
    return transfer_labels(vertices, src_v, src_f, lab)


# -- the garments as separate pieces -------------------------------------------------------------

def garment_pieces(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, body_vertices: np.ndarray,
                   body_faces: np.ndarray, clearance: float = 0.003, min_share: float = 0.05,
                   exclude: np.ndarray | None = None, cut_outline: bool = True, max_gap: float = 0.25,
                   joins: list | None = None, gap_vertices: np.ndarray | None = None,
                   evidence: np.ndarray | None = None, evidence_weight: float = 4.0, widen: int = 0,
                   fill_bowties: int = 2) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """[(label, vertices [n, 3], faces [m, 3])] one open surface per garment label: the faces
    at least two of whose corners carry it (a strap one or two vertices wide stays joined; a
    vertex of another label between two separate parts of it joins them, :func:`join_parts`) and
    none of which is in ``exclude`` [n] (a hull's bridges: cloth ends at its hem), without bow-tie
    vertices (each first given its missing faces, ``fill_bowties`` rounds; the faces at those left
    removed) or small pieces, every vertex at least ``clearance`` outside the body (moved along
    the body's normal when not). A strap cut over the shoulder is joined again across the body
    (at most ``max_gap`` long, 0: not; :func:`gaps.close_gaps`, on ``gap_vertices`` when given: the
    same joins for the same mesh elsewhere; along the segmentation's per-vertex garment log-odds
    ``evidence`` when given, the band ``widen`` rings wider than its way), each join appended to
    ``joins``."""
    from ...capture import check_template_mesh
    from .gaps import close_gaps
    from ...geometry.closest import MeshQuery

    q = MeshQuery(body_vertices, body_faces, spacing=0.02)
    out = []
    for g in sorted(set(labels.tolist()) - {LABEL_BODY}):
        lab_g = join_parts(labels == g, faces, exclude)
        keep = lab_g[faces].sum(1) >= 2
        if max_gap > 0:
            lab_g, band, info = close_gaps(lab_g, vertices if gap_vertices is None else gap_vertices, faces, exclude,
                                           max_gap=max_gap, evidence=evidence, evidence_weight=evidence_weight,
                                           widen=widen)
            keep = (lab_g[faces].sum(1) >= 2) | band[faces].all(1)
            if joins is not None:
                joins.extend({"garment": int(g), **{k: v for k, v in j.items() if k != "way"}} for j in info)
        if exclude is not None:
            keep &= ~exclude[faces].any(1)
        for r in range(fill_bowties + 10):  # a vertex joining separate fans of faces (a bow-tie):
            ids, F = _face_submesh(faces, keep)  # its missing faces are added (``fill_bowties``
            V = vertices[ids]  # rounds: a strap that meets the rest at a vertex stays joined), then
            bad = _bowtie_vertices(F, len(V))  # the faces at those left go, until none is left
            if not len(bad):
                break
            if r < fill_bowties:
                add = np.isin(faces, ids[bad]).any(1) & ~keep
                if exclude is not None:
                    add &= ~exclude[faces].any(1)
                keep |= add
                continue
            fk = np.flatnonzero(keep)
            keep[fk[np.isin(F, bad).any(1)]] = False
        if not keep.any():
            continue
        ids, F = _face_submesh(faces, keep)
        V = vertices[ids].copy()
        if cut_outline:
            V = _cut_outline(V, F, lab_g[ids])
        k, lab = _components(np.ones(len(V), bool), F, len(V))
        sizes = np.bincount(lab, minlength=k)
        big = sizes >= min_share * sizes.sum()
        if not big.all():
            ids2, F = _face_submesh(F, big[lab[F[:, 0]]])
            V = V[ids2]
        sd, qp, n = q.signed_distance(V)
        inside = sd < clearance
        V[inside] = qp[inside] + clearance * n[inside]
        problems = [p for p in check_template_mesh(V, F) if "non-manifold" in p]
        if problems:
            continue
        out.append((g, V, F))
    return out


def _cut_outline(V: np.ndarray, F: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """``V`` with each vertex of the piece not labelled garment (``~inner``: the third corner of a
    face two of whose corners are) moved to the mean of the midpoints of its edges to garment
    vertices: the label changes somewhere along those edges, so the cloth ends half way, not a
    whole edge out on the skin."""
    E = mesh_edges(F)
    E = np.concatenate([E, E[:, ::-1]])
    E = E[~inner[E[:, 0]] & inner[E[:, 1]]]
    if not len(E):
        return V
    out = V.copy()
    acc = np.zeros_like(V)
    cnt = np.bincount(E[:, 0], minlength=len(V)).astype(np.float64)
    np.add.at(acc, E[:, 0], 0.5 * (V[E[:, 0]] + V[E[:, 1]]))
    m = cnt > 0
    out[m] = acc[m] / cnt[m, None]
    return out


def join_parts(mask: np.ndarray, faces: np.ndarray, exclude: np.ndarray | None = None, passes: int = 3) -> np.ndarray:
    """[n] bool ``mask`` with the vertices outside it (and outside ``exclude``) that touch two of
    its separate connected parts added, ``passes`` times: a strap the segmentation broke at one
    vertex (its colour mixed with the skin beside it at the mesh's resolution) is one piece again,
    while a part's own outline, which touches only that part, is left as it is."""
    from scipy.sparse.csgraph import connected_components

    A = adjacency(faces, len(mask)).tocsr()
    out = mask.copy()
    for _ in range(passes):
        k, lab = connected_components(A[out][:, out], directed=False)
        if k < 2:
            break
        comp = np.full(len(out), -1)
        comp[out] = lab
        E = mesh_edges(faces)
        ce = np.concatenate([comp[E[:, 1]], comp[E[:, 0]]])
        ve = np.concatenate([E[:, 0], E[:, 1]])
        sel = (ce >= 0) & ~out[ve]
        if exclude is not None:
            sel &= ~exclude[ve]
        pairs = np.unique(np.stack([ve[sel], ce[sel]], 1), axis=0)
        touching = np.bincount(pairs[:, 0], minlength=len(out))
        joins = touching >= 2
        if not joins.any():
            break
        out |= joins
    return out


def _bowtie_vertices(F: np.ndarray, n: int) -> np.ndarray:
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    per_vertex = np.bincount(uniq[counts == 1].ravel(), minlength=n)
    over = np.bincount(uniq[counts > 2].ravel(), minlength=n)
    return np.flatnonzero((per_vertex > 2) | (over > 0))


def _face_submesh(faces: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertex ids, faces re-indexed on them) of the faces where ``keep`` [F] is true."""
    F = faces[keep]
    ids, inv = np.unique(F.ravel(), return_inverse=True)
    return ids, inv.reshape(-1, 3)
