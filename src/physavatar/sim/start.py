"""Where a step's Newton solve starts: the inertial prediction, or the cloth carried with the body.

Both only change the path to the step's minimiser, not the minimiser (docs/simulation.md "The
step", "Moving collider"). ``warm_start`` starts from the CCD-clipped inertial prediction when
its energy is lower; ``follow_body`` carries the cloth near the body rigidly with its closest
body triangles (:class:`SurfaceCarry`) when the body's own move is cut by CCD, which spares the
kinematic-penalty phase.
"""

from __future__ import annotations

import time

import numpy as np


class SurfaceCarry:
    """Points carried rigidly by their closest triangles of a deforming surface.

    Each point p is written as q + δ, q = Σ w_k v_k the closest point on a triangle (barycentric
    w) and δ in that triangle's orthonormal frame (first edge, in-plane normal, face normal);
    ``at(V)`` rebuilds the points on the surface posed as V. Exact for a rigid motion of each
    triangle. The closest triangle is searched among the k with the nearest centroids: not
    always the global one (a long triangle's centroid can be far), which only matters where
    the carry is a heuristic (the solver's start, checked by CCD).

    Attributes: distance [m] (|δ|), face, bary, side (+1 where p lies on the normal's side).
    """

    def __init__(self, V, F, P, k=8):
        from scipy.spatial import cKDTree

        from ..geometry import closest_point_triangle

        V, P = np.asarray(V, dtype=np.float64), np.asarray(P, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int64)
        k = min(k, len(self.F))
        _, cand = cKDTree(V[self.F].mean(1)).query(P, k=k)
        cand = cand.reshape(len(P), k)
        t = self.F[cand.ravel()]
        Pr = np.repeat(P, k, axis=0)
        w = closest_point_triangle(Pr, V[t[:, 0]], V[t[:, 1]], V[t[:, 2]])
        q = np.einsum("nk,nkd->nd", w, V[t])
        dist = np.linalg.norm(Pr - q, axis=1).reshape(len(P), k)
        j = np.argmin(dist, axis=1)
        r = np.arange(len(P))
        self.distance = dist[r, j]
        self.face = cand[r, j]
        self.bary = w.reshape(len(P), k, 3)[r, j]
        q = q.reshape(len(P), k, 3)[r, j]
        R, _ = self._frames(V)
        self.local = np.einsum("mij,mj->mi", R, P - q)
        self.side = np.where(self.local[:, 2] < 0, -1.0, 1.0)

    def _frames(self, V):
        tri = V[self.F[self.face]]  # [m, 3 (vertex), 3]
        e1 = tri[:, 1] - tri[:, 0]
        nrm = np.cross(e1, tri[:, 2] - tri[:, 0])
        e1 = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-300)
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        return np.stack([e1, np.cross(nrm, e1), nrm], axis=1), tri  # rows: the frame's axes

    def at(self, V, lift=None):
        """The carried points on the surface posed as V [Nv, 3]; ``lift`` [m] (per point) is
        added along the face normal."""
        R, tri = self._frames(np.asarray(V, dtype=np.float64))
        P = np.einsum("mk,mkd->md", self.bary, tri) + np.einsum("mij,mi->mj", R, self.local)
        if lift is not None:
            P = P + np.asarray(lift)[:, None] * R[:, 2]
        return P


def warm_start(scene, terms, free, X, x_pred, stats, weight=None):
    """Start Newton from the inertial prediction x̃ (free cloth vertices, mask ``free`` [n]),
    clipped by CCD so it stays intersection-free, when its energy under ``terms`` is below that
    of X (IPC's initial guess). Returns the start. ``weight`` [n_free] in [0, 1]: each free
    vertex goes that fraction of the way from X to x̃ (the release of carried cloth,
    :func:`release_weight`)."""
    n = len(free)
    X_pred = X.copy()
    if weight is None:
        X_pred[:n][free] = x_pred[free]
    else:
        X_pred[:n][free] += weight[:, None] * (x_pred[free] - X[:n][free])
    tc = time.perf_counter()
    alpha = scene.collision_free_stepsize(X, X_pred)
    stats.time["ccd"] += time.perf_counter() - tc
    if alpha <= 0.0:
        return X
    X_pred = X + alpha * (X_pred - X)
    scene.prepare_static(X)
    e0 = sum(t.energy(X) for t in terms)
    scene.prepare_static(X_pred)
    e1 = sum(t.energy(X_pred) for t in terms)
    return X_pred if e1 < e0 else X


def release_weight(distance, dhat, release):
    """[m] in [0, 1]: how far carried cloth at ``distance`` [m] from the body (at the step's start)
    goes back to its inertial prediction (SimSettings.follow_release): none within 2 d̂ (the
    contacts and the cloth just off them stay carried), all from ``release`` on, linear between."""
    lo = 2.0 * dhat
    return np.clip((np.asarray(distance) - lo) / max(release - lo, 1e-12), 0.0, 1.0)


def follow_body(scene, body_faces, free, settings, X_from, X_goal, x_pred, stats, lift_still=True, cut=None,
                info=None):
    """Carry the cloth along with the body from X_from to the body pose of X_goal
    (SimSettings.follow_body). Returns (X, reached): X_goal's body with the carried cloth
    when every leg of the move is collision-free (reached = True), else X_from moved by
    the collision-free part of the move (reached = False).

    Free cloth vertices (mask ``free`` [n]) within ``follow_body`` of the body move rigidly with
    their closest body triangle (SurfaceCarry), fading to x_pred (the inertial prediction;
    None = stay) at twice that distance. The body's vertices move on straight lines, a carried
    point on a rotating triangle does not, and a straight cloth path dips towards the triangle
    by ~θ²L/8 (tens of µm, more than the µm gaps of resting contacts): the cloth follows its
    triangles through ``follow_segments`` intermediate body poses, each leg CCD-checked.
    Cloth in an active contact (within d̂, from the barrier's collision set) is also lifted
    off along the triangle normal, up to ``follow_lift`` × d̂ by the end: those gaps would
    not survive the small non-rigid distortions of the carry; the free phase settles it
    back in a few iterations. ``lift_still=False``: not where the carrying triangle stays put
    nor carried (sim.lag: cloth pinched where the body is held back stays exactly where it is).
    ``cut``: a list that gets the leg (X_seg, X_next) whose CCD cut the move. ``info``: a dict
    that gets "distance" [n_free], each free cloth vertex's distance to the body at X_from.
    """
    s = settings
    n = len(free)
    free = np.flatnonzero(free)
    b0 = X_from[n:]
    x = X_from[:n][free]
    x_end = x if x_pred is None else x_pred[free]
    tq = time.perf_counter()
    outer = getattr(scene, "outer_faces", None)  # this step's collision surface (crease.outer_surface)
    carry = SurfaceCarry(b0, body_faces if outer is None else outer, x)
    if info is not None:
        info["distance"] = carry.distance
    weight = np.clip(2.0 - carry.distance / s.follow_body, 0.0, 1.0)[:, None]
    gap = np.full(n, np.inf)  # per cloth vertex: the closest active contact it is part of
    scene.prepare_static(X_from)
    coll = scene.collisions_at(X_from)
    E, Fa = scene.mesh.edges, scene.mesh.faces
    for group in (coll.vv_collisions, coll.ev_collisions, coll.ee_collisions, coll.fv_collisions):
        for c in group:
            ids = [i for i in c.vertex_ids(E, Fa) if i >= 0]
            cloth = [i for i in ids if i < n]
            gap[cloth] = np.minimum(gap[cloth], np.sqrt(max(c.compute_distance(X_from[ids].ravel()), 0.0)))
    gap = np.minimum(gap[free], carry.distance)
    lift = np.clip(s.follow_lift * s.dhat + scene.dmin - gap, 0.0, None) * carry.side
    if not lift_still:
        moves = np.linalg.norm(X_goal[n:] - b0, axis=1)[carry.F[carry.face]].max(axis=1)
        lift = np.where(moves > 0, lift, 0.0)
        weight = np.where(moves[:, None] > 0, weight, 0.0)  # exactly where it is (a carry rounds)
    stats.time["contact"] += time.perf_counter() - tq
    X_seg = X_from
    K = max(1, int(s.follow_segments))
    for k in range(1, K + 1):
        t = k / K
        X_next = X_goal.copy() if k == K else X_from + t * (X_goal - X_from)
        carried = carry.at(X_next[n:], lift=t * lift)
        X_next[:n][free] = weight * carried + (1.0 - weight) * (x + t * (x_end - x))
        tc = time.perf_counter()
        alpha = scene.collision_free_stepsize(X_seg, X_next)
        stats.time["ccd"] += time.perf_counter() - tc
        if alpha < 1.0:
            if cut is not None:
                cut.append((X_seg, X_next))
            return X_seg + alpha * (X_next - X_seg), False
        X_seg = X_next
    return X_seg, True


REPAIR_LIMIT = 0.03  # m: a start that needs a vertex moved farther than this is refused


def repair_start(x, faces, body_vertices, body_faces, dhat: float, limit: float = REPAIR_LIMIT,
                 clearance: float = 1.5, iters: int = 60, seams=None):
    """Push a cloth that touches or slightly crosses the body out of it, to at least d̂.

    The simulator needs an intersection-free start with every cloth–body distance above 0 (the
    barrier is infinite at contact); a drape made elsewhere often touches the body or crosses it
    in a few triangles. Each round moves every cloth vertex closer to the body than
    ``clearance`` × d̂ (or inside it: signed distance by the body's normals, geometry.MeshQuery) to
    that distance outside along the body normal at its closest point, moves the three vertices
    of a cloth triangle a body vertex is closer than that to along that body
    vertex's normal, and lets each moved vertex's unmoved neighbours follow halfway (so no
    spike is made), until ipctk finds no intersection and its minimum distance (vertex–triangle
    and edge–edge) is at least d̂. The vertices of a seam (``seams`` [S, 2] pairs) move together
    (by their mean move), so a repair opens no seam. Slight self-intersections of the cloth are
    undone first (:func:`untangle`); the report's ``self_crossings`` gives the crossing
    edge–triangle pairs before and after (a real tangle is left: self-contact is then off).

    Args:
        x: [N, 3] cloth start; faces: [F, 3]; body_vertices: [Nb, 3]; body_faces: [Fb, 3].
        dhat: the barrier's activation distance [m]; limit: the largest move allowed [m].
    Returns:
        (x [N, 3], report dict: moved_vertices, max_move, mean_move [m] (over moved vertices),
        rounds, min_distance [m], limit).
    Raises:
        PhysavatarError(None, ...) when a vertex would move more than ``limit`` or no
        intersection-free start is reached.
    """
    from scipy.spatial import cKDTree

    from ..errors import PhysavatarError
    from ..geometry import MeshQuery, adjacency
    from .contact import ContactScene

    x0 = np.asarray(x, dtype=np.float64)
    x = x0.copy()
    F = np.asarray(faces, dtype=np.int64)
    B = np.asarray(body_vertices, dtype=np.float64)
    BF = np.asarray(body_faces, dtype=np.int64)
    n = len(x)
    body = MeshQuery(B, BF)
    A = adjacency(F, n)
    scene = ContactScene(x0, F, B, BF, dhat)
    target = clearance * dhat
    group = count = None
    if seams is not None and len(seams):
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        pairs = np.asarray(seams, dtype=np.int64).reshape(-1, 2)
        _, group = connected_components(sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                                                      shape=(n, n)), directed=False)
        count = np.bincount(group, minlength=n).astype(float)
    x, tangle = untangle(x, F, seams, limit=limit)  # slight self-intersections first
    rounds, dist = 0, 0.0
    for rounds in range(iters + 1):
        X = np.vstack([x, B])
        scene.prepare_static(X)
        crossing = scene.has_intersections(X)
        dist = scene.min_distance(X)
        sd, q, nrm = body.signed_distance(x, max_dist=4 * target)
        if not crossing and dist >= dhat and sd.min() > 0:  # (a cloth wholly inside crosses nothing)
            break
        if rounds == iters:
            raise PhysavatarError(None, f"the start crosses the body and {iters} rounds of pushing the cloth out "
                                        "did not separate them")
        delta = np.zeros_like(x)

        def propose(idx, d, delta=delta):
            longer = np.linalg.norm(d, axis=1) > np.linalg.norm(delta[idx], axis=1)
            delta[idx[longer]] = d[longer]

        bad = np.flatnonzero(sd < target)
        propose(bad, q[bad] + nrm[bad] * (1.25 * target) - x[bad])
        # body vertices near (or through) the cloth: move the cloth triangle they face
        near = np.isfinite(cKDTree(x).query(B, distance_upper_bound=4 * target + _longest_edge(x, F))[0])
        if near.any():
            bi = np.flatnonzero(near)
            d, f, _, cq = MeshQuery(x, F).closest(B[bi], max_dist=4 * target)
            side = np.einsum("nd,nd->n", cq - B[bi], body.normals[bi])
            low = d < target  # close (a cloth point "behind" a body vertex farther away is concavity, not a crossing)
            push = body.normals[bi[low]] * (1.25 * target + np.maximum(-side[low], 0.0))[:, None]
            for k in range(3):
                propose(F[f[low], k], push)
        if not (np.abs(delta).sum(1) > 0).any():  # an edge–edge contact only: widen the band pushed out
            target *= 1.5
            continue
        moved = (np.abs(delta).sum(1) > 0).astype(float)
        spread = (A @ delta) / np.maximum(A @ moved, 1.0)[:, None]
        step = np.where(moved[:, None] > 0, delta, 0.5 * spread)
        if group is not None:  # seam vertices: one move per seam point
            mean = np.zeros((n, 3))
            np.add.at(mean, group, step)
            step = mean[group] / count[group][:, None]
        x = x + step
        worst = float(np.linalg.norm(x - x0, axis=1).max())
        if worst > limit:
            raise PhysavatarError(None, f"the start crosses the body by more than the repair limit: a vertex would "
                                        f"move {worst * 1000:.1f} mm > {limit * 1000:.1f} mm")
    move = np.linalg.norm(x - x0, axis=1)
    moved = move > 0
    report = {"moved_vertices": int(moved.sum()), "max_move": float(move.max()),
              "mean_move": float(move[moved].mean()) if moved.any() else 0.0, "rounds": int(rounds),
              "min_distance": float(dist), "limit": float(limit),
              "self_crossings": {"before": tangle["self_crossings_before"],
                                 "after": tangle["self_crossings_after"] if not tangle["self_crossings_before"]
                                 else len(self_crossings(x, F, seams))}}
    return x, report


def _longest_edge(x, F):
    return float(np.linalg.norm(x[F] - x[F[:, [1, 2, 0]]], axis=2).max())


def self_crossings(x, faces, seams=None) -> np.ndarray:
    """[K, 2] (edge, triangle) pairs of a cloth that cross each other (ipctk's exact
    edge–triangle test on the pairs whose bounding spheres overlap); an edge and a triangle that
    share a vertex, or a sewn point (``seams`` [S, 2]: the panels meet there), are not a crossing.
    Edges are :func:`physavatar.geometry.mesh_edges`' order."""
    import ipctk
    from scipy.spatial import cKDTree

    from ..geometry import mesh_edges

    x = np.asarray(x, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    E = mesh_edges(F)
    pid = _sewn_ids(len(x), seams)
    a, b = x[E[:, 0]], x[E[:, 1]]
    mid, r_e = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=1)
    tri = x[F]
    cen = tri.mean(1)
    r_t = np.linalg.norm(tri - cen[:, None], axis=2).max(1)
    lists = cKDTree(cen).query_ball_point(mid, r_e + r_t.max())
    out = []
    PF, PE = pid[F], pid[E]
    for i, cand in enumerate(lists):
        if not cand:
            continue
        cand = np.asarray(cand)
        cand = cand[(np.linalg.norm(cen[cand] - mid[i], axis=1) <= r_e[i] + r_t[cand])
                    & ~np.isin(PF[cand], PE[i]).any(1)]
        out += [(i, t) for t in cand if ipctk.is_edge_intersecting_triangle(a[i], b[i], *tri[t])]
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def _sewn_ids(n, seams):
    if seams is None or not len(seams):
        return np.arange(n)
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    s = np.asarray(seams, dtype=np.int64).reshape(-1, 2)
    return connected_components(sp.coo_matrix((np.ones(len(s)), (s[:, 0], s[:, 1])), shape=(n, n)), directed=False)[1]


def untangle(x, faces, seams=None, rounds: int = 30, limit: float = REPAIR_LIMIT):
    """Undo slight self-intersections of a cloth (a fold poking through its neighbour layer, a
    corner of a drape through the next panel): while :func:`self_crossings` finds crossing pairs,
    the vertices of the crossing edges and triangles and their neighbours move halfway to the mean
    of their neighbours (a local Laplacian smoothing: a vertex poked through another layer is
    pulled back to its own), a sewn point as one. Returns (x, report: crossings before and after,
    rounds, moved vertices, largest move [m]); a crossing that would need a move beyond ``limit``
    (a real tangle) is left (after > 0) and the cloth kept as it was."""
    from ..geometry import adjacency, mesh_edges

    x0 = np.asarray(x, dtype=np.float64)
    x = x0.copy()
    F = np.asarray(faces, dtype=np.int64)
    E = mesh_edges(F)
    n = len(x)
    pid = _sewn_ids(n, seams)
    A = adjacency(F, n)
    deg = np.maximum(np.asarray(A.sum(1)).ravel(), 1.0)
    count = np.bincount(pid, minlength=n).astype(float)
    pairs = self_crossings(x, F, seams)
    before = len(pairs)
    r = 0
    for r in range(1, rounds + 1):
        if not len(pairs):
            r -= 1
            break
        hit = np.zeros(n, bool)
        hit[E[pairs[:, 0]].ravel()] = True
        hit[F[pairs[:, 1]].ravel()] = True
        region = hit | (A @ hit.astype(float) > 0)
        region = np.isin(pid, pid[region])  # a sewn point moves as one
        step = np.where(region[:, None], 0.5 * ((A @ x) / deg[:, None] - x), 0.0)
        mean = np.zeros((n, 3))
        np.add.at(mean, pid, step)
        x = x + mean[pid] / count[pid][:, None]
        if np.linalg.norm(x - x0, axis=1).max() > limit:
            x = x0
            pairs = self_crossings(x, F, seams)
            break
        pairs = self_crossings(x, F, seams)
    move = np.linalg.norm(x - x0, axis=1)
    return x, {"self_crossings_before": int(before), "self_crossings_after": int(len(pairs)), "rounds": int(r),
               "moved_vertices": int((move > 0).sum()), "max_move": float(move.max()) if n else 0.0}
