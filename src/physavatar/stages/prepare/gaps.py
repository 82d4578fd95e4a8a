"""Cut straps joined again (session 30): a strap that lies on the skin over the shoulder is one
vertex wide at the prepared mesh's edge length, and a segmentation (or the true labels moved onto
the reconstructed surface) that labels a few of its vertices body cuts it, so the back of a dress
hangs from nothing. Such a cut leaves a garment part whose top ends in the open: a vertex with no
garment above it within ``top_reach`` through the garment (a local top). :func:`close_gaps` joins
each local top to the nearest garment vertex across the body (the shortest way over vertices
outside the garment, at most ``max_gap`` long) that lies higher (the way climbs at least ``climb``
of its length) and is far through the garment (over ``ratio`` times the gap, or not reached): the
cut strap's other end. The join is a band: the way's vertices and ``widen`` rings of vertices
around them are garment (session 31: one ring, prepare's default, makes it about a strap's width
at 2-cm edges, 4-6 cm; the way alone, session 30's, is about one edge; the demo's 1-s drape of
the free part dropped 112 mm with it, 98 with the ring, the original dress 89), plus the third
corners of the way's edges' faces, whose faces the cut keeps. The way is the shortest; with the
segmentation's evidence (``evidence``, ``evidence_weight`` > 0) the cheapest at a cost that
grows where the images say body (on the demo it does not bring the way closer to the true strap,
which the shortest way already follows in plan: off by default). Not specific to a garment: a
hem, a hole in the cloth (its way round about 1.6 times across) or a neckline's side (no climb to
a garment above it) is left as it is; z is up, as everywhere in the project."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from ...geometry.mesh import adjacency, mesh_edges


def _graph(E: np.ndarray, w: np.ndarray, sel: np.ndarray, n: int) -> sp.csr_matrix:
    e, ww = E[sel], w[sel]
    return sp.coo_matrix((np.r_[ww, ww], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()


def local_tops(mask: np.ndarray, vertices: np.ndarray, faces: np.ndarray, reach: float) -> np.ndarray:
    """[k] the garment vertices (``mask``) with no garment vertex higher within ``reach`` through
    the garment and a garment neighbour (not a stray vertex)."""
    V = np.asarray(vertices, np.float64)
    E = mesh_edges(faces)
    inside = mask[E[:, 0]] & mask[E[:, 1]]
    deg = np.bincount(E[inside].ravel(), minlength=len(V))
    # a top is higher than every garment neighbour: the candidates, then their reach
    higher = np.zeros(len(V), bool)
    e = E[inside]
    higher[e[V[e[:, 1], 2] > V[e[:, 0], 2], 0]] = True
    higher[e[V[e[:, 0], 2] > V[e[:, 1], 2], 1]] = True
    cand = np.flatnonzero(mask & ~higher & (deg >= 1))
    if not len(cand):
        return cand
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    d = dijkstra(_graph(E, w, inside, len(V)), indices=cand, limit=reach)
    zmax = np.where(np.isfinite(d), V[:, 2][None, :], -np.inf).max(1)
    return cand[zmax <= V[cand, 2]]


def close_gaps(mask: np.ndarray, vertices: np.ndarray, faces: np.ndarray, exclude: np.ndarray | None = None,
               max_gap: float = 0.25, ratio: float = 2.0, climb: float = 0.3,
               top_reach: float = 0.1, evidence: np.ndarray | None = None,
               evidence_weight: float = 4.0, widen: int = 0) -> tuple[np.ndarray, np.ndarray, list]:
    """(``mask`` [n] with each join's way added, band [n] bool: the ways and the third corners of
    their edges' faces, [{'gap': m, 'through_garment': m, or None where the garment does not
    reach it within ``ratio`` × ``max_gap``, 'climb': m, 'vertices': k, 'way':
    vertex ids}] per join). Ways run over vertices outside ``mask`` and ``exclude`` (a hull's
    bridges); see the module's docstring for which local tops are joined to what. Of local tops
    within ``top_reach`` of each other through the garment (a strap's top two vertices wide) the
    one with the shortest gap is joined. Which tops join is decided on lengths; with ``evidence``
    [n] (the segmentation's garment log-odds per vertex) the way itself is the cheapest at a cost
    of length × (1 + ``evidence_weight`` × the body probability, sigmoid(-evidence), of its ends),
    to any of the garment vertices the join's conditions allow: it runs where the images say
    cloth (the strap's line), not straight across the skin (:func:`_evidence_ways`)."""
    V = np.asarray(vertices, np.float64)
    n = len(V)
    mask = np.asarray(mask, bool)
    out, band = mask.copy(), np.zeros(n, bool)
    allowed = np.ones(n, bool) if exclude is None else ~np.asarray(exclude, bool)
    E = mesh_edges(faces)
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    inside = mask[E[:, 0]] & mask[E[:, 1]]
    across = ~inside & allowed[E[:, 0]] & allowed[E[:, 1]]
    tops = local_tops(mask, V, faces, top_reach)
    tops = tops[allowed[tops]]
    info = []
    if not len(tops):
        return out, band, info
    da, pred_a = dijkstra(_graph(E, w, across, n), indices=tops, limit=max_gap, return_predecessors=True)
    dw, pred = da, pred_a
    if evidence is not None and evidence_weight > 0:
        dw, pred = _evidence_ways(E, w, across, mask, tops, evidence, evidence_weight, max_gap)
    dg = dijkstra(_graph(E, w, inside, n), indices=tops, limit=ratio * max_gap)
    Fs = np.sort(np.asarray(faces), axis=1)
    A = adjacency(faces, n).tocsr()
    best = np.where(mask[None, :] & (dg > ratio * da) & (V[None, :, 2] - V[tops, 2][:, None] >= climb * da), da, np.inf)
    joined: list[int] = []
    for i in np.argsort(best.min(1)):  # the shortest first; a top beside a joined one is not joined again
        u = tops[i]
        if any(dg[i, t] <= top_reach for t in joined):
            continue
        ok = mask & np.isfinite(da[i]) & (dg[i] > ratio * da[i]) & (V[:, 2] - V[u, 2] >= climb * da[i])
        ok[u] = False
        if not ok.any():
            continue
        d_i, p_i = (dw[i], pred[i]) if np.isfinite(dw[i][ok]).any() else (da[i], pred_a[i])
        v = int(np.argmin(np.where(ok, d_i, np.inf)))
        way = [v]
        while way[-1] != u:
            way.append(int(p_i[way[-1]]))
        way = np.asarray(way[::-1])
        joined.append(u)
        out[way] = True
        band[way] = True
        for a, b in zip(way[:-1], way[1:]):  # the third corners of the faces on the way's edges
            e0, e1 = min(a, b), max(a, b)
            on = ((Fs[:, 0] == e0) & ((Fs[:, 1] == e1) | (Fs[:, 2] == e1))) | ((Fs[:, 1] == e0) & (Fs[:, 2] == e1))
            band[Fs[on].ravel()] = True
        ring = np.zeros(n, bool)
        ring[way] = True
        for _ in range(widen):  # the band ``widen`` rings wider than the way: garment, about a strap's width
            ring |= (A @ ring.astype(np.int8)) > 0
            ring &= allowed
        out |= ring
        band |= ring
        through = round(float(dg[i, v]), 4) if np.isfinite(dg[i, v]) else None  # JSON has no inf
        length = float(np.linalg.norm(np.diff(V[way], axis=0), axis=1).sum())
        info.append({"gap": round(length, 4), "shortest": round(float(da[i].min(where=ok, initial=np.inf)), 4),
                     "through_garment": through,
                     "climb": round(float(V[v, 2] - V[u, 2]), 4), "vertices": int(len(way)), "way": way.tolist()})
    band &= allowed
    return out, band, info


def _evidence_ways(E: np.ndarray, w: np.ndarray, across: np.ndarray, mask: np.ndarray, tops: np.ndarray,
                   evidence: np.ndarray, weight: float, max_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """([k, n] cost, [k, n] predecessors) of the cheapest ways from each of ``tops`` over the
    ``across`` edges at length × (1 + ``weight`` × the mean body probability of the edge's ends).
    A way leaves the garment (``mask``) only at its top: it does not run along the garment's
    outline, in and out of it (whose vertices are cheap), to reach its end."""
    q = 1.0 / (1.0 + np.exp(np.clip(np.asarray(evidence, np.float64), -30, 30)))  # P(body)
    c = w * (1.0 + weight * 0.5 * (q[E[:, 0]] + q[E[:, 1]]))
    src = np.zeros(len(mask), bool)
    src[tops] = True
    e, cc = E[across], c[across]
    a, b = np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]]
    keep = ~mask[a] | src[a]  # directed: out of a garment vertex only at a top
    n = len(mask)
    G = sp.coo_matrix((np.r_[cc, cc][keep], (a[keep], b[keep])), shape=(n, n)).tocsr()
    return dijkstra(G, directed=True, indices=tops, limit=(1.0 + weight) * max_gap, return_predecessors=True)
