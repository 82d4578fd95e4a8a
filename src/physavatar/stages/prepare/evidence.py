"""Evidence the segmentation (segment.py) adds to its distance, colour and body-under terms, and
the guard on what it may change.

* :func:`photo_term`: whether the hull refinement found a photo-consistent textured surface at
  each vertex (refine.photo_depths), as learned log-odds;
* :func:`keep_topology`: the labelling with the evidence, reached from the one without it by
  removing only simple vertices, so a garment is trimmed but never cut or holed.
"""

from __future__ import annotations

import numpy as np

from ...geometry.mesh import adjacency
from .config import SegmentConfig


def photo_term(logit: np.ndarray, photo: np.ndarray, faces: np.ndarray, cfg: SegmentConfig) -> tuple[np.ndarray, dict]:
    """``logit`` plus the log-likelihood ratio of each vertex's photo-consistency evidence (``photo``
    [V]: 1 where the cameras agree on a textured surface point at the vertex, 0 where two or more
    cameras see it and they do not, NaN where fewer see it: refine.photo_depths), the two rates
    counted on the vertices the other terms already decide (``|logit| > 2``), with one pseudo-count
    each way. A patterned garment is photo-consistent where it is; plain skin, and the empty space a
    visual hull bridges over bare skin (between a dress's straps, under the arms), are not. For a
    plain garment the two rates agree and the term vanishes."""
    ok = np.isfinite(photo)
    e = ok & (photo > 0.5)
    for _ in range(cfg.photo_rings):  # evidence within this many rings: a strap's patches straddle its edges
        e = ok & (e | (adjacency(faces, len(e)) @ e.astype(np.float64) > 0))
    g, b = ok & (logit > 2), ok & (logit < -2)
    info = {"evidence": int(e.sum()), "seen_by_two": int(ok.sum())}
    if g.sum() < 20 or b.sum() < 20:
        return logit, info
    pg, pb = (e[g].sum() + 1) / (g.sum() + 2), (e[b].sum() + 1) / (b.sum() + 2)
    llr = np.where(e, np.log(pg / pb), np.log((1 - pg) / (1 - pb)))
    llr = cfg.photo_weight * np.clip(np.where(ok, llr, 0.0), -cfg.photo_cap, cfg.photo_cap)
    return logit + llr, info | {"garment_rate": round(float(pg), 3), "body_rate": round(float(pb), 3)}


def keep_topology(before: np.ndarray, after: np.ndarray, faces: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, int]:
    """``after`` (a garment mask) reached from ``before`` by taking away, one vertex at a time in
    ``order`` (the surest body first), only vertices whose removal does not change the garment's
    topology: simple vertices, whose garment neighbours form one arc of their ring (not none: a
    piece would vanish; not the whole ring: a hole; not two or more: a cut), repeated until none
    is left (topology-preserving thinning; Bertrand's simple points on a surface mesh). Evidence
    may trim a garment's edge (skin the hull bridged above a neckline) but not cut through it (a
    strap, whose patches straddle its edges and find less photo-consistency) or punch a hole in
    it. Vertices ``after`` adds are added. Returns the mask and how many were kept."""
    lost = before & ~after
    out = before | after
    if not lost.any():
        return after, 0
    # each vertex's ring: the edges opposite it in its faces
    opp = {}
    for f in faces[lost[faces].any(1)]:
        for i in range(3):
            v = int(f[i])
            if lost[v]:
                opp.setdefault(v, []).append((int(f[(i + 1) % 3]), int(f[(i + 2) % 3])))

    def simple(v: int) -> bool:
        ring = opp.get(v, [])
        nodes = {a for e in ring for a in e}
        inside = {a for a in nodes if out[a]}
        if not inside or len(inside) == len(nodes):
            return False
        parent = {a: a for a in inside}

        def find(a):
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            return a

        for a, b in ring:
            if a in inside and b in inside:
                parent[find(a)] = find(b)
        return len({find(a) for a in inside}) == 1

    cand = [int(v) for v in order if lost[v]]
    changed = True
    while changed:
        changed = False
        for v in cand:
            if out[v] and simple(v):
                out[v] = False
                changed = True
    return out, int((out & lost).sum())
