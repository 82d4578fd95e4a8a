"""Boundary vertices: where each garment stays on the body (waistband, shoulder straps).

Automatic (:func:`find_boundary`): a garment vertex is **in contact** when it lies within
``contact`` of the fitted body in the first frame, and **moves with the body** when, carried
with its closest body point through the sampled frames (the body's own motion, no cloth), it
stays inside the masks of at least ``inside`` of the cameras in every one of them: a garment
point that swings away from the body (a hem, a loose panel) leaves the silhouette of where the
body would carry it; one held by the body does not. Garments hang from the highest place they
are held, so of the contact regions (connected on the garment) those reaching within
``top_band`` of the garment's highest contact are kept: the waistband of a skirt or trousers,
the shoulders of a dress, not a hull's bridge between a hem and the legs. The band is in height;
with ``grow_along`` > 0 (default 0) the holds then grow that far along the garment over the
contact vertices (a strap that drops steeply down the back of the shoulder is held beyond the
band's height there).

Override (``--boundary FILE``): a PLY whose vertices carry a ``boundary`` property, or a .npy /
.txt of 3D points; garment vertices within ``radius`` of those points are the boundary.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import PhysavatarError
from ...geometry.mesh import adjacency
from .config import BoundaryConfig


def _project_inside(points: np.ndarray, cameras: list, masks: dict[str, np.ndarray]) -> np.ndarray:
    """[n] share of the cameras (those the point projects into) whose mask holds it."""
    hits = np.zeros(len(points))
    seen = np.zeros(len(points))
    for c in cameras:
        uv, z = c.project(points)
        uv = np.nan_to_num(uv)
        x, y = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        ok = (z > 1e-6) & (x >= 0) & (x < c.width) & (y >= 0) & (y < c.height)
        m = masks[c.name]
        hits[ok] += m[y[ok], x[ok]] > 0.5
        seen += ok
    return np.where(seen > 0, hits / np.maximum(seen, 1), 0.0)


def carried_support(vertices: np.ndarray, body_frames: np.ndarray, body_faces: np.ndarray, cameras: list,
                    masks_of: callable) -> tuple[np.ndarray, tuple]:
    """[n] the smallest share, over the sampled frames after the first, of the cameras whose mask
    holds each vertex when it is carried with its closest body point (1: it stays in every
    silhouette, as a point the body holds does); and the closest-point query (d, face, bary, point)."""
    from ...geometry.closest import MeshQuery

    d, f, w, q = MeshQuery(body_frames[0], body_faces, spacing=0.02).closest(vertices)
    offset = vertices - q
    worst = np.ones(len(vertices))
    for i in range(1, len(body_frames)):
        carried = np.einsum("nk,nkd->nd", w, body_frames[i][body_faces[f]]) + offset
        worst = np.minimum(worst, _project_inside(carried, cameras, masks_of(i)))
    return worst, (d, f, w, q)


def find_boundary(vertices: np.ndarray, faces: np.ndarray, body_frames: np.ndarray, body_faces: np.ndarray,
                  cameras: list, masks_of: callable, frame_index: list[int], cfg: BoundaryConfig
                  ) -> tuple[np.ndarray, dict]:
    """[n] bool boundary of one garment piece (``vertices``, ``faces``), and the numbers behind it.
    Each connected part of the piece gets its own holds; a part other than the largest with no
    vertex in contact that follows the body is a fragment the segmentation cut off (it would fall
    away under gravity in the simulation): ``info["_unheld"]`` [n] marks its vertices, to be
    dropped.

    ``body_frames``: [S, Nb, 3] the body at the sampled frames (first = the template's frame);
    ``masks_of(i)``: {camera: [H, W]} masks of sampled frame ``i``.
    """
    from scipy.sparse.csgraph import connected_components

    k, lab = connected_components(adjacency(faces, len(vertices)), directed=False)
    if k <= 1:
        return _find_boundary(vertices, faces, body_frames, body_faces, cameras, masks_of, cfg)
    out = np.zeros(len(vertices), bool)
    unheld = np.zeros(len(vertices), bool)
    largest = int(np.argmax(np.bincount(lab, minlength=k)))
    infos = []
    for c in range(k):
        ids = np.flatnonzero(lab == c)
        fsel = (lab[faces] == c).all(1)
        remap = np.full(len(vertices), -1)
        remap[ids] = np.arange(len(ids))
        b, info = _find_boundary(vertices[ids], remap[faces[fsel]], body_frames, body_faces, cameras, masks_of, cfg)
        if c != largest and "fallback" in info:
            unheld[ids] = True
            continue
        out[ids] = b
        infos.append(info)
    total = {key: sum(i.get(key, 0) for i in infos) for key in ("contact", "follows", "candidates", "boundary",
                                                                 "regions_kept", "regions")}
    return out, total | {"parts": k, "dropped_vertices": int(unheld.sum()), "_unheld": unheld}


def _find_boundary(vertices, faces, body_frames, body_faces, cameras, masks_of, cfg: BoundaryConfig):
    worst, (d, _, _, _) = carried_support(vertices, body_frames, body_faces, cameras, masks_of)
    contact = d < cfg.contact
    follows = worst >= cfg.inside
    cand = contact & follows
    info = {"contact": int(contact.sum()), "follows": int(follows.sum()), "candidates": int(cand.sum())}
    if not cand.any():  # nothing is held: the highest contact band, else the garment's top
        cand = contact if contact.any() else vertices[:, 2] >= vertices[:, 2].max() - cfg.top_band
        info["fallback"] = "contact only" if contact.any() else "top of the garment"
    from scipy.sparse.csgraph import connected_components

    idx = np.flatnonzero(cand)
    A = adjacency(faces, len(vertices))[idx][:, idx]
    k, lab = connected_components(A, directed=False)
    sizes = np.bincount(lab, minlength=k)
    big = sizes >= min(cfg.min_region, sizes.max())  # a lone vertex is no hold
    top = vertices[idx[big[lab]], 2].max()
    reach = np.zeros(k, bool)
    np.maximum.at(reach, lab, vertices[idx, 2] >= top - cfg.top_band)
    reach &= big
    out = np.zeros(len(vertices), bool)
    # a hold is the part of a kept region within the band: where a tight bodice stays in contact
    # from the straps down to the hips, the region is one, and the whole bodice is no hold
    out[idx[reach[lab] & (vertices[idx, 2] >= top - cfg.top_band)]] = True
    if cfg.grow and out.any():  # the whole hold: the contact around what was kept, in the band
        near = np.flatnonzero(contact & (vertices[:, 2] >= top - cfg.top_band))
        k2, lab2 = connected_components(adjacency(faces, len(vertices))[near][:, near], directed=False)
        hit = np.zeros(k2, bool)
        np.maximum.at(hit, lab2, out[near])
        out[near[hit[lab2]]] = True
        # grown over contact above the followed part (straps a fitted body carries a few pixels
        # out of a side view's mask): the hold is the band under the grown region's top
        out &= vertices[:, 2] >= vertices[out, 2].max() - cfg.top_band
    if cfg.grow_along > 0 and out.any():
        out = along_garment(vertices, faces, out, contact, cfg.grow_along)
    info["boundary"] = int(out.sum())
    info["regions_kept"] = int(reach.sum())
    info["regions"] = int(k)
    return out, info


def along_garment(vertices: np.ndarray, faces: np.ndarray, seed: np.ndarray, allowed: np.ndarray,
                  reach: float) -> np.ndarray:
    """[n] bool: ``seed`` and the ``allowed`` vertices within ``reach`` of it along the garment's
    edges (shortest paths through allowed vertices; scipy's Dijkstra)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    A = adjacency(faces, len(vertices)).tocoo()
    ok = (seed | allowed)[A.row] & (seed | allowed)[A.col]
    i, j = A.row[ok], A.col[ok]
    G = sp.csr_matrix((np.linalg.norm(vertices[i] - vertices[j], axis=1), (i, j)), shape=A.shape)
    dist = dijkstra(G, directed=False, indices=np.flatnonzero(seed), min_only=True)
    return seed | (allowed & (dist <= reach * (1 + 1e-6)))


def boundary_points(path: Path) -> np.ndarray:
    """[n, 3] the points of a ``--boundary`` file."""
    from ...files import read_ply

    path = Path(path)
    if not path.is_file():
        raise PhysavatarError(path, "boundary file not found")
    if path.suffix.lower() == ".ply":
        ply = read_ply(path)
        if "boundary" not in ply.vertex_data:
            raise PhysavatarError(path, "PLY has no per-vertex 'boundary' property")
        pts = ply.vertices[np.asarray(ply.vertex_data["boundary"]).astype(bool)]
    else:
        try:
            pts = np.load(path) if path.suffix.lower() == ".npy" else np.loadtxt(path, ndmin=2)
        except Exception as e:  # noqa: BLE001 - any parse failure is the file's problem
            raise PhysavatarError(path, f"unreadable boundary points ({type(e).__name__})") from None
        pts = np.asarray(pts, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise PhysavatarError(path, f"must hold 3D points (n × 3), got shape {list(pts.shape)}")
    if not len(pts):
        raise PhysavatarError(path, "no boundary points")
    return pts


def boundary_from_points(vertices: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """[n] bool: vertices within ``radius`` of any of ``points``."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(vertices)
    return d <= radius


def boundary_error(chosen: np.ndarray, true: np.ndarray) -> dict:
    """Distances between chosen and true boundary points [m]: each chosen point to the nearest
    true one (mean, max) and each true one to the nearest chosen (mean: coverage)."""
    from scipy.spatial import cKDTree

    if not len(chosen) or not len(true):
        return {"chosen_to_true_mean": float("inf"), "chosen_to_true_max": float("inf"),
                "true_to_chosen_mean": float("inf")}
    a, _ = cKDTree(true).query(chosen)
    b, _ = cKDTree(chosen).query(true)
    return {"chosen_to_true_mean": float(a.mean()), "chosen_to_true_max": float(a.max()),
            "true_to_chosen_mean": float(b.mean())}
