"""The body's own creases: cloth collides with the body's outer surface only.

Anny's collider passes through itself where two of its parts press together (the groin on the
CMU walk, the back of the knee on the hop, the armpits and fingers at rest): a belly triangle
and a thigh triangle cross. Cloth between two such parts is caught in a wedge that closes to
nothing, no intersection-free cloth position has the body at its pose, and the step gives up
(the body lags, sim.lag). The body's real surface there is the *union* of its parts: a triangle
that lies inside the body is not surface at all.

So, per step (:func:`outer_surface`, called by ``ClothSim.step`` before the step's start) while
``ClothSim.crease_on`` (off by default, as the rule in every step lets cloth slide into the body
where nothing pinches it; ``sim.simulate`` turns it on only for the attempts after one of the
frame lagged without it, so a frame that does not pinch is simulated as before):

- a body vertex is *buried* when it lies inside the body mesh at the step's start or at its end:
  the generalised winding number of the body mesh at the vertex (Jacobson et al. 2013; its own
  incident triangles subtend no solid angle, the rest of its own part about ½) is above 1, i.e.
  another part encloses it. The buried set is grown by one ring (``SimSettings.crease_ring``), so
  that every triangle with a buried corner has all three corners buried: ipctk skips a primitive
  pair only when every pair of its vertices is filtered, so a triangle that straddles the
  intersection curve (the wedge's sides) goes only when all its corners do;
- a free cloth vertex is *released* when it lies inside the body at the step's start (winding
  number of the body mesh above ½): cloth that an earlier step left inside a part (it crossed a
  triangle that was buried then) moves out under its own elasticity and gravity, unhindered by
  the triangles it is behind;
- contact leaves out every cloth–body vertex pair with a buried body vertex or a released cloth
  vertex or one of its neighbours (RELEASE_RING; an ipctk CollisionFilter composed with the
  scene's own, in C++). Cloth–cloth contact is unchanged.

A step without buried body vertices near the cloth or released cloth vertices keeps the scene's
own filter object: on a body that does not pass through itself near the cloth the simulation is
bit-identical. The step stays intersection-free (CCD) against every pair it does collide with;
the body's buried triangles are inside the body, so cloth crossing them does not show.

With ``ClothSim.crease_visible`` (off; docs/simulation.md "Session 26") the body is hidden by
primitive instead (:class:`VisibleContact`, a candidate filter): only the primitives with a
buried corner, and those straddling the crossing curve only where the cloth faces their hidden
part. It keeps the cloth on the visible part of the triangles next to a crease, but where the
buried part sinks deep (the hop's knee) the cloth is then pinched there instead of crossing.
"""

from __future__ import annotations

import ipctk
import numpy as np

from ..geometry.winding import winding_number
from .terms import Diagonal, Term

BURIED = 1.0  # winding number above which a body vertex is inside another part (its own: ~0.5)
INSIDE = 0.5  # above which a cloth vertex is inside the body
RELEASE_RING = 1  # rings of cloth around a released vertex released with it (no pull): an edge from a
# vertex inside to one outside crosses the body surface, and with its outside end still in contact the
# body's edges sliding along it are cut by CCD (the pinch of walk frame 99: docs/simulation.md "Session 21")


def body_creases(s, body0, body1, faces, cloth) -> bool:
    """Whether the body passes through itself within reach of the cloth at the start or the end
    of a frame (body0 → body1 [Nb, 3], faces [Fb, 3], cloth [N, 3]; ``s``: SimSettings): whether the outer-surface rule would
    leave anything out (sim.simulate retries a frame that lagged with it only then)."""
    from scipy.spatial import cKDTree

    if s.crease_ring < 0 or body0 is None or not len(body0):
        return False
    B0, B1 = np.asarray(body0, np.float64), np.asarray(body1, np.float64)
    reach = np.linalg.norm(B1 - B0, axis=1) + s.follow_body + 2 * s.dhat
    d0, _ = cKDTree(np.asarray(cloth, np.float64)).query(B0, distance_upper_bound=float(reach.max()))
    near = d0 <= reach
    return bool(near.any() and (buried_vertices(B0, faces, near).any() or buried_vertices(B1, faces, near).any()))


PARALLEL_WORK = 2e7  # point-triangle pairs (~0.35 s serial) above which the winding loop runs on every core


def winding_numbers(points, vertices, faces, vertex_ids=None) -> np.ndarray:
    """Winding number of the mesh at points (``geometry.winding_number``); a point that is mesh
    vertex ``vertex_ids[i]`` leaves out its own triangles. Serial, or numba's parallel loop
    over the points once there are more than PARALLEL_WORK point–triangle pairs (each point's
    sum in the same order either way: the same bits; ~1 s a call on the 13.7k-vertex full
    body, docs/simulation.md "Session 21")."""
    work = len(points) * len(faces)
    return winding_number(points, vertices, faces, vertex_ids, parallel=work > PARALLEL_WORK)


class _BodyWinding:
    """The winding numbers of a body mesh at its own vertices, kept for the last few body
    poses (a frame's end pose is the next frame's start: ``body_creases`` and
    ``outer_surface`` ask for both), computed only for the vertices not asked before."""

    def __init__(self, size=4):
        self.size, self.entries = size, {}

    def at(self, V, F, ids):
        key = (V.shape, F.shape, hash(V.tobytes()), hash(F.tobytes()))
        entry = self.entries.pop(key, None)
        if entry is None or not (np.array_equal(entry[0], V) and np.array_equal(entry[1], F)):
            entry = (V.copy(), F.copy(), np.full(len(V), np.nan))
        self.entries[key] = entry  # most recent last
        w = entry[2]
        while len(self.entries) > self.size:
            self.entries.pop(next(iter(self.entries)))
        todo = ids[np.isnan(w[ids])]
        if len(todo):
            w[todo] = winding_numbers(V[todo], V, F, todo)
        return w[ids]


_BODY_WINDING = _BodyWinding()


def buried_vertices(vertices, faces, near=None, seeds=None) -> np.ndarray:
    """bool [V]: the body vertices inside another part of the body (winding number > BURIED),
    among those ``near`` (bool [V]; default all). With ``seeds`` (bool [V]) only the seeds are
    tested, and then, ring by ring, the neighbours of every vertex found buried (a buried region
    is bounded by the curve where the parts cross, next to which the seeds must lie)."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    near = np.ones(len(V), bool) if near is None else np.asarray(near, bool)
    out = np.zeros(len(V), bool)
    test = near.copy() if seeds is None else (near & seeds)
    done = np.zeros(len(V), bool)
    while test.any():
        ids = np.flatnonzero(test)
        done[ids] = True
        out[ids] = _BODY_WINDING.at(V, F, ids) > BURIED
        if seeds is None:
            break
        ring = np.zeros(len(V), bool)
        hit = out[F].any(axis=1)
        ring[F[hit].ravel()] = True
        test = ring & near & ~done
    return out


def grow(mask, faces, rings: int) -> np.ndarray:
    """``mask`` grown by ``rings`` rings of the mesh ``faces``: a vertex joins when one of its
    triangles has a vertex in the mask."""
    F = np.asarray(faces, dtype=np.int64)
    out = np.asarray(mask, bool).copy()
    for _ in range(rings):
        hit = out[F].any(axis=1)
        out[F[hit].ravel()] = True
    return out


def outer_filter(n_cloth: int, n_body: int, hidden) -> ipctk.CollisionFilter:
    """ipctk filter rejecting every cloth–body vertex pair with a vertex in ``hidden`` (stacked
    ids [cloth; body]), allowing the rest (cloth–cloth and body–body pairs included)."""
    side = np.r_[np.zeros(n_cloth), np.ones(n_body)].astype(np.int32)
    cross = ipctk.make_vertex_patches_filter(side)  # one cloth and one body vertex
    patch = np.zeros(n_cloth + n_body, np.int32)
    hidden = np.asarray(hidden, dtype=np.int64)
    patch[hidden] = np.arange(1, len(hidden) + 1)
    either = ipctk.make_vertex_patches_filter(patch)  # at least one of the two is hidden
    return ~(cross & either)


def outer_surface(sim, X_start, X_goal, free) -> tuple[int, int]:
    """Set the scene's contact filter for one step (module docstring): (buried body vertices,
    released cloth vertices). ``X_start``, ``X_goal``: the stacked [cloth; body] positions at the
    step's start and the prescribed ones at its end; ``free``: bool [N], the free cloth vertices."""
    scene, n = sim.scene, sim.n
    base = getattr(scene, "base_filter", None)
    if base is None:
        base = scene.base_filter = scene.mesh.can_collide
    s = sim.settings
    scene.mesh.can_collide, scene.outer_faces = base, None
    scene.candidate_filter = None
    if s.crease_ring < 0 or not sim.nb:  # off: the body as it is, every triangle collides
        return 0, 0
    faces = sim._body_faces
    cloth = X_start[:n]
    B0, B1 = X_start[n:], X_goal[n:]
    buried0 = buried1 = np.zeros(sim.nb, bool)
    near = np.zeros(sim.nb, bool)
    if sim.crease_on:
        # only the body within reach of the cloth in this step can matter
        from scipy.spatial import cKDTree

        reach = np.linalg.norm(B1 - B0, axis=1) + s.follow_body + 2 * s.dhat
        d0, _ = cKDTree(cloth).query(B0, distance_upper_bound=float(reach.max()))
        near = d0 <= reach
    if np.any(near):
        buried0, buried1 = buried_vertices(B0, faces, near), buried_vertices(B1, faces, near)
    buried = buried0 | buried1
    hidden_body = np.flatnonzero(grow(buried, faces, s.crease_ring)) if buried.any() else np.zeros(0, np.int64)
    if sim.crease_visible and len(hidden_body):  # by primitive, the visible part kept (VisibleContact)
        hidden_body = np.flatnonzero(buried)
        scene.candidate_filter = VisibleContact(sim, buried, cloth, B0, B1)
    F = np.asarray(faces, np.int64)
    # the body's collision surface this step: its triangles without a hidden corner (follow_body
    # carries cloth with these only)
    scene.outer_faces = F[~np.isin(F, hidden_body).any(axis=1)] if len(hidden_body) else None
    # released: free cloth inside the body at the start
    # (only while a crease is near or the last step released cloth: otherwise the last step
    # collided with the whole surface from a start outside it, and no cloth can be inside; the
    # flag is part of ClothSim.get_state, so a retried or resumed step is the same)
    inside = crossing = np.zeros(n, bool)
    ids = np.flatnonzero(free)
    if len(ids) and (sim._crease_check or len(hidden_body)):
        inside[ids] = winding_numbers(cloth[ids], B0, faces) > INSIDE
    lift = None
    if len(ids) and (sim._crease_check or len(hidden_body)):
        # and the cloth that crosses the body's outer surface with its corners outside (a body
        # edge through a cloth triangle, a cloth edge through a body triangle between its
        # corners): lifted above the crossing
        outer = F if scene.outer_faces is None else scene.outer_faces
        lift = crossing_cloth(cloth, sim.topo.faces, B0, outer, s.dhat + 0.5 * sim.dmin)  # 2 d̂ beyond d_min
        crossing = np.all(np.isfinite(lift), axis=1) & free & ~inside
        inside = inside | crossing
    released = np.flatnonzero(inside)
    sim._crease_check = bool(len(hidden_body) or len(released))
    pull = _release_term(sim)
    if len(released):
        # pulled out to the outer surface at the step's end; their one-ring is released from the
        # body too (an edge from a vertex inside to one outside crosses the body surface: its
        # edge–edge pairs with body edges would stop the vertex at the first body edge)
        # (the outer surface at the end: without the triangles buried there)
        at_end = np.flatnonzero(grow(buried1, faces, s.crease_ring)) if buried1.any() else np.zeros(0, np.int64)
        target = np.empty((len(released), 3))
        deep = ~crossing[released]
        target[deep] = outside_targets(cloth[released[deep]], B1, faces, at_end, s.dhat + 0.5 * sim.dmin)
        target[~deep] = lift[released[~deep]]
        pull.set(released, target,
                 sim.inertia.unit_mass[released] * sim.material.density / sim.h_implicit**2)
        if pull not in sim.terms:
            sim.terms.append(pull)
        released = np.flatnonzero(grow(inside, sim.topo.faces, RELEASE_RING) & free)
    elif pull in sim.terms:
        sim.terms.remove(pull)
    if scene.candidate_filter is not None:
        if len(released):
            scene.mesh.can_collide = base & outer_filter(n, sim.nb, released)
    elif len(hidden_body) or len(released):
        scene.mesh.can_collide = base & outer_filter(n, sim.nb, np.r_[released, n + hidden_body])
    return int(buried.sum()), len(released)


RELEASE_PULL = 1e3  # the pull's weight on a released cloth vertex, × its mass / h² (the inertia's)


class ReleasePull(Term):
    """(w_i/2) Σ ‖x_i − t_i‖² over the released cloth vertices (inside the body at the step's
    start): pulls each to ``t_i``, 2 d̂ outside the closest point of the body's outer surface.
    The body cannot push them out (they are released from its contact), so this does, as a
    soft penalty (w_i = RELEASE_PULL × m_i / h²); in the solver's terms only while there are any."""

    parameter = "density"

    def __init__(self, n_total: int):
        self.n_total = n_total
        self.ids = np.zeros(0, np.int64)
        self.target = np.zeros((0, 3))
        self.weight = np.zeros(0)

    def set(self, ids, target, mass_over_h2):
        self.ids, self.target = np.asarray(ids, np.int64), np.asarray(target, np.float64)
        self.weight = RELEASE_PULL * np.asarray(mass_over_h2, np.float64)

    def energy(self, X):
        d = X[self.ids] - self.target
        return 0.5 * float(np.sum(self.weight[:, None] * d * d))

    def gradient(self, X):
        out = np.zeros((self.n_total, 3))
        out[self.ids] = self.weight[:, None] * (X[self.ids] - self.target)
        return out.ravel()

    def hessian(self, X, project=True):
        diag = np.zeros((self.n_total, 3))
        diag[self.ids] = self.weight[:, None]
        return Diagonal(diag.ravel())


def _release_term(sim) -> ReleasePull:
    n_total = sim.n + sim.nb
    term = getattr(sim, "_release_pull", None)
    if term is None or term.n_total != n_total:
        if term is not None and term in sim.terms:
            sim.terms.remove(term)
        term = sim._release_pull = ReleasePull(n_total)
    return term


def outside_targets(points, body, faces, hidden, dhat):
    """2 d̂ outside the closest point of the body's outer surface (its triangles without a
    hidden corner) to each point (geometry.MeshQuery), along that triangle's normal."""
    from ..geometry.closest import MeshQuery

    F = np.asarray(faces, np.int64)
    keep = np.ones(len(body), bool)
    keep[hidden] = False
    F = F[keep[F].all(axis=1)]
    _, face, _, q = MeshQuery(body, F, spacing=0.02).closest(points)
    tri = np.asarray(body)[F[face]]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    return q + 2.0 * dhat * nrm


def crossing_cloth(cloth, cloth_faces, body, body_faces, dhat, visible_in=None) -> np.ndarray:
    """[N, 3]: per cloth vertex, where it must go so that the cloth no longer crosses the body's
    surface with its corners outside (NaN: nowhere). The crossings both ways
    (``geometry.intersecting_pairs``: a cloth edge through a body triangle, a body edge through a
    cloth triangle). At a crossing point p with the body's outward normal there (the triangle's,
    or the mean of the edge's two triangles') each vertex of the cloth primitive that lies below
    2 d̂ above p's tangent plane is lifted to 2 d̂ above it. ``visible_in`` (V [Nb, 3], F [Fb', 3]):
    only the crossings at points p outside every other part of that body mesh, i.e. on its
    visible surface; a crossing inside another part is hidden, and the cloth edge there crosses
    the visible surface elsewhere too. The winding number is taken a hair (d̂/1000) outside p
    along the normal, where the crossed triangle adds ~0 and another part ~1: at p itself the
    crossed triangle adds +½ or −½ by rounding (session 26)."""
    from ..geometry.intersect import intersecting_pairs

    cloth, body = np.asarray(cloth, np.float64), np.asarray(body, np.float64)
    Fc, Fb = np.asarray(cloth_faces, np.int64), np.asarray(body_faces, np.int64)
    tri = body[Fb]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    out = np.full((len(cloth), 3), np.nan)
    cloth_edges, body_edges = intersecting_pairs(cloth, Fc, body, Fb)
    crossings = [(cloth[e], body[Fb[t]], e, fn[t]) for e, t in cloth_edges]
    for e, t in body_edges:  # the body edge's outward normal: the mean of its triangles'
        n = fn[(np.isin(Fb, e).sum(axis=1) == 2)].sum(axis=0)
        crossings.append((body[e], cloth[Fc[t]], Fc[t], n / max(np.linalg.norm(n), 1e-30)))
    points = []
    for (a, b), (t0, t1, t2), _, _ in crossings:
        tn = np.cross(t1 - t0, t2 - t0)
        with np.errstate(divide="ignore", invalid="ignore"):  # an edge in the triangle's plane: NaN, no lift
            points.append(a + float(np.dot(t0 - a, tn) / np.dot(b - a, tn)) * (b - a))  # the crossing point
    shown = np.ones(len(points), bool)
    if visible_in is not None and len(points):
        outside = np.array(points) + 1e-3 * dhat * np.array([c[3] for c in crossings])
        shown = winding_numbers(outside, *visible_in) < 0.5
    for (_, _, lifted, normal), p, keep in zip(crossings, points, shown):
        if not keep:
            continue
        for i in lifted:
            x = out[i] if np.all(np.isfinite(out[i])) else cloth[i]
            depth = 2.0 * dhat - float(np.dot(x - p, normal))
            if depth > 0:
                out[i] = x + depth * normal
    return out


class VisibleContact:
    """A crease step's body contact by primitive (``ContactScene.candidate_filter``): a body
    vertex, edge or triangle with no buried corner collides as usual, one with every corner
    buried not at all, and one that straddles the curve where the parts cross (some corners
    buried) collides with a cloth primitive only where the closest point between the two at the
    step's start lies on its visible part: outside every other part of the body at the step's
    start and its end (the body's winding number there, its own triangles left out, below
    BURIED). Decided once per pair for the step (from the step's start), so the filter is the
    same at every build and the step's CCD holds against every pair it keeps."""

    def __init__(self, sim, buried, cloth0, body0, body1):
        self.n, self.nfc = sim.n, len(sim.topo.faces)
        self.buried = np.asarray(buried, bool)
        self.cloth0, self.B0, self.B1 = cloth0, body0, body1
        self.Fb = np.asarray(sim._body_faces, np.int64)
        self.keep = {}  # (0, body face, cloth vertex) / (1, body edge, cloth edge) -> bool
        self.dropped = 0

    def _decide(self, todo, scene):
        import ipctk

        n, E, F = self.n, scene.mesh.edges, scene.mesh.faces
        pts0, pts1, skip = [], [], []
        for kind, b, c in todo:
            if kind == 0:
                tri = F[b] - n
                u, v = ipctk.point_triangle_closest_point(self.cloth0[c], *self.B0[tri])
                u, v = min(max(u, 0.0), 1.0), min(max(v, 0.0), 1.0)
                w = np.array([1.0 - u - v, u, v])
                ids = tri
            else:
                ids = E[b] - n
                g = E[c]
                t, _ = ipctk.edge_edge_closest_point(self.B0[ids[0]], self.B0[ids[1]], self.cloth0[g[0]], self.cloth0[g[1]])
                t = min(max(t, 0.0), 1.0)
                w = np.array([1.0 - t, t])
            pts0.append(w @ self.B0[ids])
            pts1.append(w @ self.B1[ids])
            skip.append(ids[~self.buried[ids]][0])  # its own triangles left out: a corner outside
        skip = np.array(skip)
        w0 = winding_numbers(np.array(pts0), self.B0, self.Fb, skip)
        w1 = winding_numbers(np.array(pts1), self.B1, self.Fb, skip)
        for key, a, b in zip(todo, w0, w1):
            self.keep[key] = bool(a < BURIED and b < BURIED)

    def __call__(self, scene):
        n, nfc, bur = self.n, self.nfc, self.buried
        E, F = scene.mesh.edges, scene.mesh.faces
        cand = scene.candidates
        fv, ee = cand.fv_candidates, cand.ee_candidates
        fv_ids = np.array([(k.face_id, k.vertex_id) for k in fv], np.int64).reshape(-1, 2)
        ee_ids = np.array([(k.edge0_id, k.edge1_id) for k in ee], np.int64).reshape(-1, 2)
        buried = np.r_[np.zeros(n, bool), bur]  # over the stacked [cloth; body] vertices
        # a body triangle and a cloth vertex (the pair's key: 0, triangle, vertex), or a cloth
        # triangle and a body vertex (dropped where that is buried)
        f, v = fv_ids[:, 0], fv_ids[:, 1]
        body_face = f >= nfc
        corners = buried[F[f]].sum(axis=1)
        keep_fv = np.where(body_face, corners == 0, ~buried[v])
        straddle_fv = np.flatnonzero(body_face & (corners > 0) & (corners < 3))
        # a body edge and a cloth edge (key: 1, body edge, cloth edge); cloth–cloth pairs kept
        a, b = ee_ids[:, 0], ee_ids[:, 1]
        swap = E[a, 0] < n
        body_e, cloth_e = np.where(swap, b, a), np.where(swap, a, b)
        cross = (E[a, 0] < n) != (E[b, 0] < n)
        ends = buried[E[body_e]].sum(axis=1)
        keep_ee = ~cross | (ends == 0)
        straddle_ee = np.flatnonzero(cross & (ends == 1))
        keys = [(0, int(f[i]), int(v[i])) for i in straddle_fv] + [(1, int(body_e[i]), int(cloth_e[i])) for i in straddle_ee]
        todo = [k for k in keys if k not in self.keep]
        if todo:
            self._decide(todo, scene)
        keep_fv[straddle_fv] = [self.keep[k] for k in keys[:len(straddle_fv)]]
        keep_ee[straddle_ee] = [self.keep[k] for k in keys[len(straddle_fv):]]
        if not keep_fv.all():
            cand.fv_candidates = [k for k, ok in zip(fv, keep_fv) if ok]
        if not keep_ee.all():
            cand.ee_candidates = [k for k, ok in zip(ee, keep_ee) if ok]
        self.dropped = int((~keep_fv).sum() + (~keep_ee).sum())
