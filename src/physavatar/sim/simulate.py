"""A whole sequence: a garment simulated on a moving body frame after frame (``simulate``).

Sub-stepping is decided per frame (:func:`substep_count`): a frame in which the body near the
cloth moves more than ``SimSettings.max_body_move`` is split into more implicit steps (up to
``max_substeps``), and a frame whose step still gives up (the body *lags*, StepStats.body_gap)
is simulated again from its start with twice the steps, until ``max_substeps``; only then is the
lag kept (reported per frame). An attempt that such a retry follows stops at its first lagging
step (its result is discarded anyway), and its penalty phases give up once they stall
(ClothSim.stall_exit), so the retry comes sooner (docs/simulation.md "Why the whole clips
stalled"). After every frame a :class:`Checkpoint` (positions, velocities and the solver's
state) can be taken, and ``resume=`` continues from one with the same result as an
uninterrupted run (docs/simulation.md "Never lose work").
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path

import ipctk
import numpy as np

from ..files import load_npz, save_npz_atomic
from ..progress import ProgressLike, resolve
from .collapse import crosses, uncollapse
from .crease import body_creases
from .material import Material
from .settings import SimSettings
from .solver import ClothSim
from .untangle import held_body, untangle_frame_end


@dataclasses.dataclass
class Checkpoint:
    """The state of a simulation after ``frame``: cloth positions and velocities (float64) and
    ``ClothSim.get_state()`` (adaptive barrier stiffness, BDF2 history, body lag, step length)."""

    frame: int
    x: np.ndarray
    v: np.ndarray
    solver: dict

    def save(self, path: str | Path) -> Path:
        """Write atomically as .npz (float64: a resumed run continues from the same bits)."""
        arrays = {"frame": np.int64(self.frame), "x": self.x, "v": self.v,
                  "solver_scalars": np.asarray(json.dumps(
                      {k: v for k, v in self.solver.items() if np.ndim(v) == 0}, default=float))}
        arrays |= {f"solver_{k}": v for k, v in self.solver.items() if np.ndim(v) > 0}
        save_npz_atomic(Path(path), **arrays)
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "Checkpoint":
        z = load_npz(Path(path))
        solver = json.loads(str(z["solver_scalars"]))
        solver |= {k[len("solver_"):]: np.asarray(z[k]) for k in z if k.startswith("solver_") and k != "solver_scalars"}
        return cls(int(z["frame"]), np.asarray(z["x"], np.float64), np.asarray(z["v"], np.float64), solver)


def substep_count(body0, body1, cloth, settings: SimSettings, min_substeps: int = 1, max_substeps: int = 1,
                  tree=None) -> tuple[int, float]:
    """(implicit steps for one frame, how far the body near the cloth moves in it [m]).

    A body vertex can reach the cloth within the frame when its distance to the nearest cloth
    vertex is below its own move plus ``settings.follow_body`` (the reach of the carry that
    starts each step, start.follow_body); the largest move among those vertices, over
    ``settings.max_body_move``, rounded up, is the count (clamped to [min_substeps,
    max_substeps]). A body that is still, or moves away from the cloth's reach, gets
    ``min_substeps``. ``tree``: a scipy cKDTree of ``cloth`` (built here when None).
    """
    body0 = np.asarray(body0, dtype=np.float64)
    move = np.linalg.norm(np.asarray(body1, dtype=np.float64) - body0, axis=1)
    if not len(move) or max_substeps <= min_substeps:
        return min_substeps, float(move.max()) if len(move) else 0.0
    if tree is None:
        from scipy.spatial import cKDTree

        tree = cKDTree(np.asarray(cloth, dtype=np.float64))
    reach = move + settings.follow_body + settings.dhat
    dist, _ = tree.query(body0, distance_upper_bound=float(reach.max()))
    near = dist <= reach
    m = float(move[near].max()) if np.any(near) else 0.0
    n = math.ceil(m / settings.max_body_move - 1e-9) if m > 0 else 1
    return int(min(max(n, min_substeps), max_substeps)), m


def seam_exclusions(faces, seams, n_vertices: int | None = None) -> np.ndarray:
    """[P, 2] cloth vertex pairs (i < j) that self-contact must leave out for sewn seams.

    Sewn panels meet at seam vertex pairs (sim.stitch: coincident, or stitched closed) that are
    separate vertices of the mesh, so the triangles on either side of a seam touch at distance 0
    without sharing a vertex, and the barrier could never be evaluated there. Out go the pairs of
    the seam vertices' closed one-rings across each seam: for every two vertices a, b joined by
    seams (directly or through a third panel), every p in {a} ∪ ring(a) with every q in
    {b} ∪ ring(b). ipctk skips an edge–edge or face–vertex pair when every pair of their vertices
    is left out, so exactly the primitives that touch at the seam line are skipped; the rest of
    the panels, one ring away from the seam, collide as usual.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    seams = np.asarray(seams if seams is not None else np.zeros((0, 2)), dtype=np.int64).reshape(-1, 2)
    F = np.asarray(faces, dtype=np.int64)
    if not len(seams):
        return np.zeros((0, 2), np.int64)
    n = int(n_vertices if n_vertices is not None else max(F.max(), seams.max()) + 1)
    e = np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    ring = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), (n, n)).tocsr()
    ring = ((ring + sp.identity(n, format="csr")) > 0).astype(np.float64)  # closed one-rings
    S = sp.coo_matrix((np.ones(len(seams)), (seams[:, 0], seams[:, 1])), (n, n))
    _, comp = connected_components(S, directed=False)  # vertices joined by seams, through any panel
    sewn = np.unique(seams)
    groups = sp.coo_matrix((np.ones(len(sewn)), (sewn, comp[sewn])), (n, n)).tocsr()
    same = (groups @ groups.T).tocsr()  # a ~ b: joined by seams
    same.setdiag(0)  # (a = b is not a pair across a seam)
    same.eliminate_zeros()
    pairs = sp.triu(ring @ same @ ring, k=1).tocoo()
    keep = pairs.data > 0
    return np.c_[pairs.row[keep], pairs.col[keep]].astype(np.int64)


def feasible_thickness(sim, x, body, body_faces):
    """(start, settings) for ``sim``'s contact thickness (Material.contact_offset, SimSettings.dmin):
    ``x`` lifted where a contact pair with the body is closer than the thickness plus d̂/2 (ipctk's
    barrier is undefined closer than d_min), and where that cannot be done the settings' thickness
    lowered to what the start allows, with a warning (sim.offset.feasible_start)."""
    from .offset import feasible_start

    s = sim.settings
    if body is None or not len(body):
        return x, s
    x, thickness, report = feasible_start(x, sim.topo.faces, body, np.asarray(body_faces, np.int64).reshape(-1, 3),
                                          sim.dmin, s.dhat, sim.boundary)
    if thickness >= sim.dmin:
        return x, s
    logging.getLogger(__name__).warning("the start has cloth %.2f mm from the body, closer than the contact offset "
                                        "%.2f mm: simulated with %.2f mm", report.get("least_pair_after_mm", 0.0),
                                        1e3 * sim.dmin, 1e3 * thickness)
    return x, dataclasses.replace(s, dmin=max(thickness, 1e-9))


def self_contact_possible(vertices, faces, dhat: float, exclude=None, warn: bool = True) -> bool:
    """Whether the garment's start leaves every pair of its own non-adjacent triangles ≥ d̂
    apart (ipctk), as self-contact needs, apart from the pairs ``exclude`` [P, 2] leaves out
    (seam_exclusions: the primitives that touch at a sewn seam). Layers closer than d̂ would
    start inside the barrier; the simulation then runs without self-contact and says so
    (config.json ``self_contact``; ``warn``: log that, where the caller does not refuse instead)."""
    from .contact import cloth_filter

    F = np.asarray(faces, np.int32)
    V = np.asarray(vertices, np.float64)
    mesh = ipctk.CollisionMesh(V, ipctk.edges(F), F)
    mesh.can_collide = cloth_filter(len(V), exclude)
    c = ipctk.NormalCollisions()
    c.build(mesh, V, dhat)
    ok = len(c) == 0
    if not ok and warn:
        logging.getLogger("physavatar.progress").warning(
            "the garment's own triangles start closer than d̂ = %g m to each other: simulated without self-contact", dhat)
    return ok


def self_intersecting_frames(X, faces, exclude=None, prescribed=None) -> list[int]:
    """Frames f of X [T, N, 3] (finite ones) where the garment intersects itself: ipctk's exact
    check on the garment alone, leaving out the pairs ``exclude`` (seam_exclusions: a sewn seam's
    two sides touch by construction) and, when ``prescribed`` [K] (the Dirichlet vertices) is
    given, the primitive pairs made of those alone (as the solver does, contact.prescribed_filter:
    what remains is what the solver answers for; their crossings are in its input)."""
    from .contact import cloth_filter, prescribed_filter

    F = np.asarray(faces, np.int32)
    X = np.asarray(X, np.float64)
    mesh = ipctk.CollisionMesh(X[0] if np.all(np.isfinite(X[0])) else np.zeros_like(X[0]), ipctk.edges(F), F)
    mesh.can_collide = cloth_filter(X.shape[1], exclude)
    if prescribed is not None and len(prescribed):
        mesh.can_collide = mesh.can_collide & prescribed_filter(X.shape[1], 0, prescribed)
    return [f for f in range(len(X)) if np.all(np.isfinite(X[f])) and ipctk.has_intersections(mesh, X[f])]


def frame_report(frame: int, stats: list, substeps: int, attempts: int, seconds: float, move: float) -> dict:
    """What a frame did (JSON-ready): steps, attempts, Newton iterations, contacts, lag."""
    gap = max((s.body_gap for s in stats), default=0.0)
    return {"frame": int(frame), "substeps": int(substeps), "attempts": int(attempts),
            "newton_iterations": int(sum(s.newton_iterations for s in stats)),
            "contacts": int(stats[-1].n_contacts) if stats else 0,
            "lag_m": float(gap), "lagged": bool(gap > 0),
            "lag_vertices": int(max((s.lag_vertices for s in stats), default=0)),
            # the body's own creases (sim.crease): body vertices left out of contact, cloth released
            "buried_vertices": int(max((s.buried_vertices for s in stats), default=0)),
            "released_vertices": int(max((s.released_vertices for s in stats), default=0)),
            # cloth moved out of the body after a pinch (sim.untangle)
            "untangled_vertices": int(sum(s.untangled_vertices for s in stats)),
            "body_move_m": round(float(move), 5),
            "seconds": round(float(seconds), 3)}


def simulate(garment_rest, faces, material: Material, collider_sequence, collider_faces,
             boundary_indices=(), boundary_targets=None, fps: float = 25.0, substeps: int = 1,
             settings: SimSettings | None = None, x0=None, v0=None, callback=None,
             progress: ProgressLike = False, max_substeps: int | None = None,
             resume: Checkpoint | None = None, on_frame=None, extra_terms=(), contact_exclude=None,
             collider_between=None):
    """Simulate a garment on a moving body for a whole sequence.

    Args:
        garment_rest: [N, 3] rest shape (also the initial state unless ``x0`` is given).
        faces: [F, 3] garment triangles.
        material: :class:`Material`.
        collider_sequence: [T, Nb, 3] body vertices per frame (frame 0 = initial pose).
        collider_faces: [Fb, 3] body triangles.
        boundary_indices: [K] Dirichlet vertices.
        boundary_targets: [T, K, 3] their positions per frame, or a callable
            ``rule(frame, body_vertices [Nb, 3]) -> [K, 3]`` (an attachment rule), or None
            (they stay at their initial positions).
        fps: frames per second of the sequence; substeps: implicit steps per frame (at least);
            max_substeps: at most (default ``substeps``: a fixed count). In between the count is
            decided per frame (:func:`substep_count`, and twice as many when a frame's step
            gave up and the body lagged). dt = 1 / (fps · steps of the frame). In between,
            the boundary targets are interpolated linearly, vertex by vertex, and so is the
            body unless ``collider_between`` is given.
        settings: :class:`SimSettings` (its dt is replaced by the one above); default: the
            defaults with the material's integrator (the one it was fitted with).
        x0, v0: [N, 3] initial positions / velocities (default rest, zero).
        callback: called as ``callback(frame, x [N, 3], stats list)`` after each frame.
        progress: anything :func:`physavatar.progress.resolve` takes (True: a terminal bar;
            a callable or a Progress: its task "simulating", one step per frame, with the
            frame's report as info; logged every 5 frames).
        resume: a :class:`Checkpoint` of an earlier run of the same simulation: continue after
            its frame (the same result as an uninterrupted run).
        on_frame: called as ``on_frame(checkpoint, report)`` after each frame (report:
            :func:`frame_report`) — where a caller writes the frame as it is finished.
        extra_terms: further terms of E (ClothSim's, e.g. a seam :class:`~physavatar.sim.stitch.Stitch`).
        contact_exclude: [P, 2] cloth vertex pairs left out of self-contact (:func:`seam_exclusions`).
        collider_between: ``between(f, s [S]) -> [S, Nb, 3]``, the body at the times f − 1 + s
            made from its poses (body.between.PoseBetween): a frame's sub-steps take their
            in-between bodies from it, plus the linear blend of the differences between the
            frames simulated (``collider_sequence``, or an uncollapsed frame, sim.collapse) and
            its s = 0 and 1, so the sequence meets those frames exactly (:func:`between_bodies`).
            None: the linear path (the only one with a single step per frame). The boundary
            targets stay on their straight line either way (riding the in-between body, they
            pinched the 2-cm dress on the CMU walk: docs/simulation.md "Session 31").

    Returns:
        [T, N, 3] garment positions per frame (frame 0 = initial state; with ``resume``, the
        frames before the checkpoint's are NaN).
    """
    settings = settings or SimSettings(integrator=material.integrator)  # the model it was fitted in
    max_substeps = substeps if max_substeps is None else max(int(max_substeps), substeps)
    settings = dataclasses.replace(settings, dt=1.0 / (fps * substeps))
    bodies = np.asarray(collider_sequence, dtype=np.float64)
    T = len(bodies)
    sim = ClothSim(garment_rest, faces, material, settings, boundary_indices, extra_terms=extra_terms,
                   contact_exclude=contact_exclude)
    sim.lag_stall_exit = True  # a lagging step's free solve ends once it stalls (a reported lag already)
    order = np.argsort(np.asarray(boundary_indices, dtype=np.int64), kind="stable")
    x = np.array(garment_rest if x0 is None else x0, dtype=np.float64)
    v = np.zeros_like(x) if v0 is None else np.array(v0, dtype=np.float64)
    x0_boundary = x[sim.boundary].copy()
    if sim.dmin > 0:  # on resume too: the same (possibly lowered) thickness; x is the checkpoint's below
        x, settings = feasible_thickness(sim, x, bodies[0], collider_faces)
        sim.settings = settings

    def targets(frame):
        if len(sim.boundary) == 0:
            return None
        if boundary_targets is None:
            return x0_boundary
        if callable(boundary_targets):
            return np.asarray(boundary_targets(frame, bodies[frame]))[order]
        return np.asarray(boundary_targets[frame])[order]

    out = np.full((T,) + x.shape, np.nan)
    # the contact scene's rest positions are the body where it is built: ipctk's edge-edge
    # mollifier thresholds come from them, so a resumed run builds it at frame 0 too, as an
    # uninterrupted one does (docs/simulation.md "Session 25")
    if T:
        sim.prepare(bodies[0], collider_faces)
    start = 1
    if resume is not None:
        start = resume.frame + 1
        x, v = resume.x.copy(), resume.v.copy()
        sim.set_state(resume.solver)
    out[start - 1] = x
    stuck = bool(resume is not None and resume.solver.get("stuck", False))
    held = np.zeros(T, bool)  # frames whose body was uncollapsed (sim.collapse): the next frame starts there
    if resume is not None and resume.solver.get("uncollapsed", False):
        bodies, held[start - 1] = _uncollapsed(bodies, start - 1, collider_faces), True
    # the body's own creases (sim.crease): on only for an attempt after one that lagged without
    # it, so a frame that does not pinch is simulated as before
    with resolve(progress).task("simulating", total=T - start, log_every=5) as task:
        for f in range(start, T):
            t0 = time.perf_counter()
            tb0, tb1 = targets(f - 1), targets(f)
            n, move = substep_count(bodies[f - 1], bodies[f], x, settings, substeps, max_substeps)
            saved = (x, v, sim.get_state())
            attempts, crease, tried = 0, False, False
            kept, moved = None, 0  # a crease attempt written through the body, while shorter steps are tried
            creasable = None if settings.crease_ring >= 0 else False  # None: not yet known
            while True:
                attempts += 1
                # an attempt that a retry in shorter steps would follow ends at its first lagging
                # step (no change: a lagged attempt is retried) and gives up a stalled penalty
                # phase early (ClothSim.stall_exit; the last attempt keeps the full budget); with a
                # crease attempt kept aside (below) a lagging attempt is discarded: it ends there too
                if creasable is None and (n >= max_substeps or stuck):
                    creasable = body_creases(sim.settings, bodies[f - 1], bodies[f], collider_faces, saved[0])
                last = (n >= max_substeps or stuck) and (crease or not creasable)
                sim.stall_exit = not last
                sim.crease_on = crease
                path = None if collider_between is None or n == 1 else between_bodies(
                    collider_between, f, n, bodies[f - 1], bodies[f])
                x, v, stats_frame = _frame(sim, x, v, bodies[f - 1], bodies[f], collider_faces, tb0, tb1, n, fps,
                                           stop_on_lag=not last or kept is not None, path=path)
                lagged = any(s.body_gap > 0 for s in stats_frame)
                if held[f] and not lagged and crosses(sim, x, original):
                    lagged = True  # clear of the uncollapsed body, through the one given: the crease rule on that
                if crease and not lagged and not last:
                    # the crease rule's cloth may end through the triangles it hid; where even the
                    # frame-end untangle leaves it crossing the body (it would be written so), the
                    # whole body in shorter steps first (docs/simulation.md "Session 33: sit-down")
                    x, moved = untangle_frame_end(sim, x, bodies[f], collider_faces)
                    if crosses(sim, x, held_body(sim, bodies[f])):
                        kept = (x, v, sim.get_state(), stats_frame, moved)
                        crease, creasable, lagged, moved = False, False, True, 0
                if last and lagged and kept is not None:
                    # the whole body lagged in the shortest steps too: the crease attempt, as before
                    x, v, state, stats_frame, moved = kept
                    sim.set_state(state)
                    lagged = False
                # a pinch that outlasted max_substeps in the last frame (no room for the cloth at
                # the body's pose: the body still short of it at the frame's end) is not undone by
                # shorter steps: no retries until a frame passes
                if not lagged or last:
                    stuck = lagged and stats_frame[-1].body_gap > 0 and (stuck or n >= max_substeps)
                    break
                if creasable is None:
                    creasable = body_creases(sim.settings, bodies[f - 1], bodies[f], collider_faces, saved[0])
                given = bodies
                if creasable and settings.uncollapse and not tried and not crease:
                    # a pinch where the body passes through itself: first on the body with its
                    # buried vertices moved out (sim.collapse), then as before
                    tried, bodies = True, _uncollapsed(bodies, f, collider_faces)
                if bodies is not given:
                    original, held[f] = given[f], True
                elif not crease and creasable:  # a pinch where the body passes through itself:
                    if held[f]:  # the crease rule on the body as it is given
                        bodies = bodies.copy()
                        bodies[f], held[f] = original, False
                    crease = True  # again, with the body's outer surface only (sim.crease)
                else:  # the body could not reach its pose: the frame again, in shorter steps
                    n = min(2 * n, max_substeps)
                x, v = saved[0], saved[1]
                sim.set_state(saved[2])
            # cloth through the body the sim holds (a step's CCD can miss an impact in a pinch):
            # moved out before the frame is written (sim.untangle; docs/simulation.md "Session 24", "Session 25")
            x, more = untangle_frame_end(sim, x, bodies[f], collider_faces)
            out[f] = x
            report = frame_report(f, stats_frame, n, attempts, time.perf_counter() - t0, move)
            report["untangled_vertices"] += moved + more
            if on_frame is not None:
                state = sim.get_state() | {"stuck": stuck} | ({"uncollapsed": True} if held[f] else {})
                on_frame(Checkpoint(f, x.copy(), v.copy(), state), report)
            if callback is not None:
                callback(f, x, stats_frame)
            task.advance(1, frame=f, s_frame=report["seconds"], newton=report["newton_iterations"],
                         contacts=report["contacts"], substeps=n, lag_mm=round(1e3 * report["lag_m"], 2))
    return out


def _uncollapsed(bodies, f: int, faces):
    """``bodies`` with frame ``f`` uncollapsed (sim.collapse; a copy where it changes)."""
    body, moved = uncollapse(bodies[f], faces)
    if not len(moved):
        return bodies
    logging.getLogger(__name__).debug("frame %d: %d buried body vertices moved out", f, len(moved))
    bodies = bodies.copy()
    bodies[f] = body
    return bodies


def between_bodies(between, f: int, n: int, body0, body1) -> np.ndarray:
    """The bodies [n + 1, Nb, 3] at the times f − 1 + k/n of a frame simulated in ``n`` steps,
    from ``between`` (simulate's ``collider_between``): its bodies plus the linear blend of
    ``body0 − between(f, 0)`` and ``body1 − between(f, 1)``, with ``body0`` and ``body1``
    themselves at k = 0 and n (bit for bit)."""
    s = np.arange(n + 1) / n
    w = s[:, None, None]
    skinned = np.asarray(between(f, s), np.float64)
    B = skinned + (1 - w) * (body0 - skinned[0]) + w * (body1 - skinned[-1])
    B[0], B[-1] = body0, body1
    return B


def _frame(sim: ClothSim, x, v, body0, body1, body_faces, tb0, tb1, n: int, fps: float, stop_on_lag=False,
           path=None):
    """One frame in ``n`` implicit steps: (x, v, StepStats of each); with ``stop_on_lag``, up to
    the first step whose body lagged. ``path``: the bodies [n + 1, Nb, 3] at the steps' ends
    (:func:`between_bodies`); None: interpolated linearly. The targets are interpolated linearly."""
    sim.set_dt(1.0 / (fps * n))
    stats = []
    for k in range(n):
        w0, w1 = k / n, (k + 1) / n
        if path is None:
            b0 = (1 - w0) * body0 + w0 * body1
            b1 = (1 - w1) * body0 + w1 * body1
        else:
            b0, b1 = path[k], path[k + 1]
        tgt = None if tb1 is None else (1 - w1) * tb0 + w1 * tb1
        x, v, st = sim.step(x, v, b0, b1, body_faces, tgt)
        stats.append(st)
        if stop_on_lag and st.body_gap > 0:
            break
    return x, v, stats
