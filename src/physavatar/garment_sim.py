"""Simulating the garment of a template on a moving body (paper Sec. 3.2, Eq. 5).

The template's garment vertices (label > 0) are the cloth; its boundary vertices are attached to
the body surface they start on (closest point, barycentric coordinates and an offset in the
triangle's frame) and follow it; the body part (label 0), posed per frame, is the collider.
Used by synthetic captures (ground-truth garment motion), ``physavatar simulate`` and animation.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from .garment import attachment_normals, attachment_positions, keep_clear, make_attachment, unfold_targets
from .sim import Material, SimSettings, simulate


@dataclass
class GarmentPart:
    """The garment of a template (or a garment file), re-indexed on its own.

    Attributes:
        vertex_ids: [N] template indices of the garment vertices.
        vertices: [N, 3] start positions on the body's first frame. faces: [F, 3] (garment-local).
        boundary: [K] garment-local indices of the Dirichlet vertices (may be empty: the garment
            is held by contact and friction alone).
        rest: [N, 3] the rest (stress-free) shape, None = ``vertices`` (a garment made in place).
        seams: [S, 2] vertex pairs sewn together (sim.stitch.Stitch), None = none.
        layer: [N] which garment of a layered system (:func:`layered`) each vertex belongs to,
            0 = the innermost; None = one garment.
    """

    vertex_ids: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    boundary: np.ndarray
    rest: np.ndarray | None = None
    seams: np.ndarray | None = None
    layer: np.ndarray | None = None

    @property
    def rest_shape(self) -> np.ndarray:
        return self.vertices if self.rest is None else self.rest

    def terms(self, stiffness: float | None = None) -> list:
        """The garment's own terms of E: its seams' stitch term, if it has seams."""
        from .sim.stitch import STITCH_STIFFNESS, Stitch

        if self.seams is None or not len(self.seams):
            return []
        return [Stitch(self.seams, STITCH_STIFFNESS if stiffness is None else stiffness)]

    def contact_exclusions(self) -> np.ndarray:
        """[P, 2] vertex pairs self-contact leaves out: the primitives that touch at its sewn
        seams (sim.simulate.seam_exclusions); none without seams."""
        from .sim.simulate import seam_exclusions

        return seam_exclusions(self.faces, self.seams, len(self.vertices))


BOUNDARY_CLEARANCE = 0.5  # × d̂: how close the boundary's own primitives may be carried to the body (keep_clear)
LAYER_GAP = 0.004  # m: the least start distance between a garment and the garments (and body) under it


def layered(parts: list[GarmentPart], body_vertices=None, body_faces=None, gap: float = LAYER_GAP) -> GarmentPart:
    """One cloth system of several garments worn over each other, ``parts`` innermost first.

    Each garment after the first is pushed out over the garments under it (:func:`push_over`)
    until it is at least ``gap`` outside them; with no body given, the parts are stacked as they
    are. Vertices, triangles, boundaries, rest shapes and seams are stacked (the garments stay
    separate components, each with its own boundary); ``layer`` says which garment a vertex is.
    The layers are then simulated together, in contact with each other through self-contact
    (SimSettings.self_contact).
    """
    placed = []
    for i, p in enumerate(parts):
        if i and body_vertices is not None:
            p = dataclasses.replace(p, vertices=push_over(p.vertices, p.faces, [(q.vertices, q.faces, q.seams) for q in placed],
                                                          body_vertices, body_faces, gap, seams=p.seams))
        placed.append(p)
    offsets = np.cumsum([0] + [len(p.vertices) for p in placed])
    seams = [p.seams + o for p, o in zip(placed, offsets) if p.seams is not None and len(p.seams)]
    rest = np.vstack([p.rest_shape for p in placed]) if any(p.rest is not None for p in placed) else None
    return GarmentPart(np.arange(offsets[-1]), np.vstack([p.vertices for p in placed]),
                       np.vstack([p.faces + o for p, o in zip(placed, offsets)]),
                       np.concatenate([p.boundary + o for p, o in zip(placed, offsets)]).astype(np.int64),
                       rest, np.vstack(seams) if seams else None,
                       np.concatenate([np.full(len(p.vertices), i) for i, p in enumerate(placed)]))


def split_layers(part: GarmentPart) -> list[GarmentPart]:
    """The garments of a layered part (:func:`layered`), innermost first, each re-indexed on its
    own (``[part]`` for a single garment)."""
    if part.layer is None:
        return [part]
    out = []
    for i in range(int(part.layer.max()) + 1):
        ids = np.flatnonzero(part.layer == i)
        remap = -np.ones(len(part.vertices), np.int64)
        remap[ids] = np.arange(len(ids))
        faces = remap[part.faces[np.all(part.layer[part.faces] == i, axis=1)]]
        seams = None
        if part.seams is not None:
            seams = remap[part.seams[np.all(part.layer[part.seams] == i, axis=1)]]
        out.append(GarmentPart(np.arange(len(ids)), part.vertices[ids], faces, remap[part.boundary[part.layer[part.boundary] == i]],
                               None if part.rest is None else part.rest[ids], seams))
    return out


def push_over(V, F, under: list, body_vertices, body_faces, gap: float = LAYER_GAP, reach: float = 0.03,
              iterations: int = 30, seams=None) -> np.ndarray:
    """A garment's vertices V [N, 3] (triangles F) moved out over the garments ``under`` (a list
    of (vertices, faces) or (vertices, faces, seams)) so that it lies at least ``gap`` outside each of them, both ways: every
    vertex of V within ``reach`` of an under-garment at least ``gap`` above its surface, and every
    under-garment vertex at least ``gap`` below V's surface. Outside is away from the body: each
    under-garment's vertex normals are turned to face away from the closest body point. A vertex
    that is too low moves out along that normal, a triangle above a poking vertex is lifted, and
    the vertices around a moved one follow halfway (the cloth stays smooth), as garment.garment.
    push_out does against a closed body (whose inside/outside test an open garment has not).
    A vertex whose closest point on the other garment is on that garment's rim (its open edges: a
    hem, a waistband, an armhole) is beside it, not under or over it: only its distance counts
    there (at least ``gap``), not its height along the normal (which would lift a dress's skirt
    below a shorter skirt's hem onto the hem, crumpling it into itself: session 31). An open edge
    both of whose ends are sewn (``seams`` [S, 2] vertex pairs, V's own; an under-garment's third
    item: a garment file's panels, stitched, not welded) is a seam, not a rim.
    """
    from .geometry import MeshQuery, adjacency, vertex_normals

    V = np.array(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    body = MeshQuery(body_vertices, body_faces)
    surfaces = []
    for Vu, Fu, *sewn in under:
        Vu, Fu = np.asarray(Vu, np.float64), np.asarray(Fu, np.int64)
        N = vertex_normals(Vu, Fu)
        _, _, _, qb = body.closest(Vu)
        N *= np.where(((Vu - qb) * N).sum(1) < 0, -1.0, 1.0)[:, None]  # away from the body
        surfaces.append((Vu, Fu, N, MeshQuery(Vu, Fu), _rim(Fu, len(Vu), sewn[0] if sewn else None)))
    A = adjacency(F, len(V))
    rim = _rim(F, len(V), seams)
    for _ in range(iterations):
        delta = np.zeros_like(V)

        def propose(idx, d):
            longer = np.linalg.norm(d, axis=1) > np.linalg.norm(delta[idx], axis=1)
            delta[idx[longer]] = d[longer]

        for Vu, Fu, N, Q, rim_u in surfaces:
            d, f, w, q = Q.closest(V, max_dist=reach)
            n = np.einsum("nk,nkd->nd", w, N[Fu[f]])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
            low = np.flatnonzero((np.where(rim_u(f, w), d < gap, d < reach)) & (((V - q) * n).sum(1) < gap))
            propose(low, q[low] + 1.25 * gap * n[low] - V[low])
            d2, f2, w2, q2 = MeshQuery(V, F).closest(Vu, max_dist=reach)
            above = ((q2 - Vu) * N).sum(1)  # how far V's surface is above each under-garment vertex
            poke = np.flatnonzero(np.where(rim(f2, w2), d2 < gap, d2 < reach) & (above < gap))
            for k in range(3):
                propose(F[f2[poke], k], N[poke] * (1.25 * gap - above[poke])[:, None])
        if not delta.any():  # vertices clear: edges and triangles too? (ipctk, at half the gap)
            for Vu, Fu, N, Q, _ in surfaces:
                for ids, up in _close_pairs(V, F, Vu, Fu, 0.5 * gap):
                    n = N[up].sum(0)
                    propose(ids, np.tile(gap * n / max(np.linalg.norm(n), 1e-30), (len(ids), 1)))
        moved = np.linalg.norm(delta, axis=1) > 0
        if not moved.any():
            break
        spread = (A @ delta) / np.maximum(A @ moved.astype(float), 1.0)[:, None]
        V += np.where(moved[:, None], delta, 0.5 * spread)
    return V


def _rim(F, n: int, seams=None):
    """A test rim(f [K], w [K, 3]) -> [K] bool: whether the closest points given by triangle f
    and barycentric coordinates w (geometry.MeshQuery.closest; exact zeros off the triangle's
    interior) lie on the mesh's open edges (edges of one triangle) or their vertices, leaving out
    the open edges both of whose ends are sewn (``seams`` [S, 2] vertex pairs: a seam of panels
    stitched together, not welded, is inside the garment)."""
    F = np.asarray(F, np.int64)
    E = np.sort(F[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    keys, count = np.unique(E[:, 0] * n + E[:, 1], return_counts=True)
    open_keys = keys[count == 1]
    if seams is not None and len(seams):
        sewn = np.zeros(n, bool)
        sewn[np.asarray(seams, np.int64).ravel()] = True
        open_keys = open_keys[~(sewn[open_keys // n] & sewn[open_keys % n])]
    on_rim = np.zeros(n, bool)
    on_rim[np.concatenate([open_keys // n, open_keys % n])] = True

    def test(f, w):
        corners = F[f]
        nz = w > 0
        k = nz.sum(1)
        out = np.zeros(len(f), bool)
        one = k == 1
        out[one] = on_rim[corners[one][nz[one]]]
        two = np.flatnonzero(k == 2)
        if len(two):
            ab = np.sort(corners[two][nz[two]].reshape(-1, 2), axis=1)
            out[two] = np.isin(ab[:, 0] * n + ab[:, 1], open_keys)
        return out

    return test


def _close_pairs(V, F, Vu, Fu, dist: float):
    """(vertex ids in V, vertex ids in Vu) of each pair of primitives, one of V's triangles, edges
    or vertices and one of Vu's, closer than ``dist`` (ipctk's collision set)."""
    import ipctk

    X = np.vstack([Vu, V])
    faces = np.vstack([Fu, np.asarray(F) + len(Vu)]).astype(np.int32)
    edges = ipctk.edges(faces)
    mesh = ipctk.CollisionMesh(X, edges, faces)
    mesh.can_collide = ipctk.make_vertex_patches_filter(np.r_[np.zeros(len(Vu)), np.ones(len(V))].astype(np.int32))
    c = ipctk.NormalCollisions()
    c.build(mesh, X, dist)
    out = []
    for k in range(len(c)):
        ids = np.asarray([i for i in c[k].vertex_ids(edges, faces) if i >= 0])
        out.append((ids[ids >= len(Vu)] - len(Vu), ids[ids < len(Vu)]))
    return out


def split_template(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, boundary: np.ndarray,
                   rest: np.ndarray | None = None):
    """(body vertex ids [Nb], body faces [Fb, 3] (body-local), GarmentPart) of a labelled mesh;
    ``rest`` [V, 3]: the garments' stress-free shape (capture template's ``rest``), None = as placed."""
    gmask = labels > 0
    body_ids = np.flatnonzero(~gmask)
    gar_ids = np.flatnonzero(gmask)
    remap = -np.ones(len(vertices), np.int64)
    remap[body_ids] = np.arange(len(body_ids))
    remap[gar_ids] = np.arange(len(gar_ids))
    fg = gmask[faces]
    if (fg.any(1) & ~fg.all(1)).any():
        raise ValueError("a face joins body and garment vertices; garments must be separate pieces")
    body_faces = remap[faces[~fg.any(1)]]
    gar_faces = remap[faces[fg.all(1)]]
    kinds = np.unique(labels[gar_ids])  # several garments (labels 1, 2, ...): layers of one cloth system
    layer = np.searchsorted(kinds, labels[gar_ids]) if len(kinds) > 1 else None
    part = GarmentPart(gar_ids, vertices[gar_ids].copy(), gar_faces, np.flatnonzero(boundary[gar_ids]),
                       None if rest is None else np.asarray(rest, np.float64)[gar_ids].copy(), layer=layer)
    return body_ids, body_faces, part


def simulate_on_body(part: GarmentPart, body_sequence: np.ndarray, body_faces: np.ndarray, material: Material,
                     fps: float, settings: SimSettings | None = None, substeps: int = 1, progress: bool = False,
                     callback=None, rest_report: dict | None = None, between=None, **options) -> np.ndarray:
    """Simulate ``part`` on a body sequence [T, Nb, 3] starting at rest; returns [T, N, 3].

    Frame 0 of the body must be the pose the garment starts on (``part.vertices``; its rest
    shape is ``part.rest_shape``, or with a material whose ``rest_shape`` is "equilibrium" and no
    designed rest shape, the one in which ``part.vertices`` is the static equilibrium on body
    frame 0: :func:`equilibrium_part`, its report into ``rest_report``). Boundary vertices follow
    the body surface point they start on; seams are held by a stitch term. ``between``: the body
    in between frames made from its poses (body.between.PoseBetween; sim.simulate's
    ``collider_between``; the boundary targets stay on their straight line); None: the linear path.
    ``options``: more of :func:`physavatar.sim.simulate`'s (max_substeps, resume, on_frame).
    """
    body_sequence = np.asarray(body_sequence, dtype=np.float64)
    part, report = equilibrium_part(part, body_sequence[0], body_faces, material, settings)
    if report is not None and rest_report is not None:
        rest_report.update(report)
    targets = None
    if len(part.boundary):
        targets, _ = boundary_targets(part, body_sequence, body_faces, (settings or SimSettings()).dhat)
    if between is not None:
        options |= {"collider_between": between}
    return simulate(part.rest_shape, part.faces, material, body_sequence, body_faces,
                    boundary_indices=part.boundary, boundary_targets=targets, fps=fps, substeps=substeps,
                    settings=settings, progress=progress, callback=callback, x0=part.vertices,
                    extra_terms=part.terms(), contact_exclude=part.contact_exclusions(), **options)



def equilibrium_part(part: GarmentPart, body, body_faces, material: Material,
                     settings: SimSettings | None = None) -> tuple[GarmentPart, dict | None]:
    """``part`` with the rest shape its ``material`` says (Material.rest_shape): with
    "equilibrium" and no designed rest shape (``part.rest``, which is kept), the one whose static
    equilibrium under gravity, its boundary pinned, on ``body`` [Nb, 3] (the pose it is placed on),
    is ``part.vertices`` (sim.rest.equilibrium_rest; seams held by their stitches). Returns (part,
    report; None where nothing was solved); a solve that missed its tolerance is logged and its
    best round kept; a garment that is not at rest in ``part.vertices`` (report["at_rest"] false:
    it moves there) keeps them as its rest shape."""
    from .sim.rest import describe, equilibrium_rest

    if material.rest_shape != "equilibrium" or part.rest is not None:
        return part, None
    X, report = equilibrium_rest(part.vertices, part.faces, material, part.boundary, body, body_faces, settings,
                                 extra_terms=part.terms(), contact_exclude=part.contact_exclusions())
    msg = describe(report, "the template")
    log = logging.getLogger("physavatar.progress")
    if not report["at_rest"]:  # moving in its first frame: no rest shape holds it there
        log.warning(msg + f"; {report['final_rms_mm']:.1f} mm RMS left: the garment is not at rest in its first "
                          "frame, simulated with it as rest shape")
        return part, report
    if report["converged"]:
        log.info(msg)
    else:
        log.warning(msg + f"; tolerance {report['tol_mm']:.2f} mm not reached: the best round is kept")
    return dataclasses.replace(part, rest=X), report


def boundary_targets(part: GarmentPart, body_sequence: np.ndarray, body_faces: np.ndarray, dhat: float):
    """(targets [T, K, 3] of ``part``'s boundary vertices on a body sequence [T, Nb, 3], report).

    Each boundary vertex rides the body triangle it starts on (garment.make_attachment, at its
    :func:`sewn_points`); in frames where the attached patch's own triangles would pass through
    each other (the skin under it folds) an as-rigid-as-possible fit of the patch replaces the
    ride (garment.unfold_targets); then the boundary's own edges are kept from being carried
    through a bending body (garment.keep_clear). The report's "attachment": the ride
    (garment.Attachment)."""
    att = make_attachment(sewn_points(part.vertices, part.boundary, part.seams), part.boundary, body_sequence[0],
                          body_faces, "sequence")
    targets = attachment_positions(att, body_sequence)
    targets, unfolded = unfold_targets(targets, part.faces, part.boundary, attachment_normals(att, body_sequence))
    log = logging.getLogger("physavatar.progress")
    if unfolded["frames_changed"]:
        log.info("attached triangles crossed in %d frames: fitted as-rigid-as-possible in %d (at most %.1f mm from "
                 "the ride; %d still cross)", len(unfolded["frames_crossing"]), unfolded["frames_changed"],
                 1e3 * unfolded["max_change_m"], len(unfolded["still_crossing"]))
    targets, lifted = keep_clear(att, targets, part.faces, body_sequence, body_faces, BOUNDARY_CLEARANCE * dhat)
    if lifted["frames_lifted"]:
        log.info("boundary targets lifted off the body in %d frames (at most %.2f mm; floor %.3f mm)",
                 lifted["frames_lifted"], 1e3 * lifted["max_lift_m"], 1e3 * lifted["floor_m"])
    return targets, {"unfold": unfolded, "keep_clear": lifted, "attachment": att}


def sewn_points(vertices, boundary, seams) -> np.ndarray:
    """[K, 3] the points the boundary vertices are attached at: their own positions, except
    that boundary vertices sewn to each other (directly or through other sewn vertices) share
    their mean. Attached separately, the two sides of a seam ride different body triangles
    (the closest point of each, µm apart, may fall on either side of a body edge) and are
    pulled apart as the body bends there; both prescribed, no stitch can close them (the
    dress's armhole seam opened to 3.8 mm on the CMU clips)."""
    V = np.asarray(vertices, np.float64)
    ids = np.asarray(boundary, np.int64)
    pts = V[ids].copy()
    if seams is None or not len(seams) or not len(ids):
        return pts
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    S = np.asarray(seams, np.int64).reshape(-1, 2)
    S = S[np.isin(S, ids).all(1)]
    if not len(S):
        return pts
    n = len(V)
    _, comp = connected_components(sp.coo_matrix((np.ones(len(S)), (S[:, 0], S[:, 1])), (n, n)), directed=False)
    c = comp[ids]
    mean = np.zeros((n, 3))
    np.add.at(mean, c, pts)
    return mean[c] / np.bincount(c, minlength=n)[c][:, None]


def simulate_on_body_job(part: GarmentPart, body_sequence: np.ndarray, body_faces: np.ndarray, material: Material,
                         fps: float, settings: SimSettings | None = None, send_frames: bool = False,
                         report=None) -> np.ndarray:
    """:func:`simulate_on_body` as a :class:`physavatar.parallel.Job`: ``report(1)`` per frame,
    with ``(frame, positions)`` as the item when ``send_frames``."""
    cb = None if report is None else (
        (lambda f, x, st: report(1, (f, x.copy()))) if send_frames else (lambda f, x, st: report(1)))
    return simulate_on_body(part, body_sequence, body_faces, material, fps, settings=settings, callback=cb)


def rest_strain(x, rest, faces) -> np.ndarray:
    """[F] per-triangle strain of positions x [N, 3] against the rest shape [N, 3]: the largest
    |σ − 1| of the deformation gradient's singular values σ (0 = the rest shape, 0.05 = 5 %)."""
    from .sim.mesh import ClothTopology

    topo = ClothTopology.build(rest, faces)
    Fd = np.einsum("fad,fak->fdk", np.asarray(x, dtype=np.float64)[topo.faces], topo.face_grad)  # [F, 3, 2]
    s = np.linalg.svd(Fd, compute_uv=False)
    return np.abs(s - 1.0).max(axis=1)


FIT_NEWTON_TOL = 1e-2  # m/s: the settling's Newton tolerance
FIT_NEWTON_ITERATIONS = 30
FIT_DAMPING = 2.0  # 1/s: mass damping while settling
FIT_REPAIR_LIMIT = 0.08  # m: the fit's start repair works against the shrunk body (a few vertices near a bone axis)


def fit_on_body(garment, body, material: Material, settings: SimSettings | None = None, frames: int = 20,
                hold: int = 10, fps: float = 25.0, repair_limit: float = 0.03, progress=False, pose_frames: int = 15,
                alignment=None):
    """Fit a garment made for another body (a garment.files.GarmentMesh) onto ``body``'s rest
    pose: align it (garment.fit.align_with_openings: limbs posed through its sleeves or trouser
    legs, else garment.fit.align_garment), repair the start against the shrunk body, simulate it
    without gravity, seams stitched, while the body grows to full size (garment.fit.growing_bodies)
    and then, over ``pose_frames``, turns its limbs back to the rest pose (or lowers its arms while
    growing), then ``hold`` frames under gravity hanging from where it rests
    (garment.boundary.auto_boundary). ``alignment``: a garment.fit.Alignment already made (the
    search skipped). Returns (GarmentPart on the rest body, with that boundary; report dict)."""
    from .errors import PhysavatarError
    from .garment.boundary import arm_vertices, auto_boundary
    from .garment.fit import align_garment, align_with_openings, growing_bodies
    from .sim.start import repair_start
    from .sim.stitch import seam_gaps

    settings = settings or SimSettings(integrator=material.integrator)
    # a settling, not a motion to reproduce: a looser Newton tolerance, a cap on iterations and
    # mass damping (the settled shape, not the path to it, is the result)
    settings = dataclasses.replace(settings, newton_tol=max(settings.newton_tol, FIT_NEWTON_TOL),
                                   max_newton_iterations=min(settings.max_newton_iterations, FIT_NEWTON_ITERATIONS),
                                   damping_mass=max(settings.damping_mass, FIT_DAMPING))
    al = alignment or align_with_openings(garment.vertices, body, garment.faces, garment.seams)
    if al is None:  # no sleeves or trouser legs
        al = align_garment(garment.vertices, body, faces=garment.faces)
    rest = garment.rest * al.grade
    try:
        bodies, alpha0 = growing_bodies(body, al, frames, hold, dhat=settings.dhat, pose_frames=pose_frames)
        # (a no-op unless the shrunk body's clearance check missed a contact)
        x0, repair = repair_start(al.vertices, garment.faces, bodies[0], body.faces, settings.dhat,
                                  max(repair_limit, FIT_REPAIR_LIMIT),
                                  seams=garment.seams)
    except PhysavatarError as e:
        raise PhysavatarError(garment.path, f"fitting onto the body: {e.problem}") from None
    part = GarmentPart(np.arange(len(x0)), x0, garment.faces, np.zeros(0, np.int64), rest, garment.seams)
    # growing without gravity (the body pushes the garment out; nothing makes it slide down the
    # shrunk body), then settling under gravity hanging from where it rests (auto boundary)
    grow = dataclasses.replace(settings, gravity=(0.0, 0.0, 0.0))
    moving = len(bodies) - hold - 1
    X = simulate_on_body(part, bodies[: moving + 1], body.faces, material, fps, settings=grow, progress=progress)
    part = dataclasses.replace(part, vertices=X[-1])
    part.boundary, _ = auto_boundary(part.vertices, part.faces, bodies[moving], body.faces, avoid=arm_vertices(body))
    if hold:
        X = simulate_on_body(part, bodies[moving:], body.faces, material, fps, settings=settings, progress=progress)
    x = X[-1]
    if not np.all(np.isfinite(x)):
        raise PhysavatarError(garment.path, "fitting onto the body: the settling simulation diverged")
    strain = rest_strain(x, rest, garment.faces)
    gaps = seam_gaps(x, garment.seams)
    report = {"alignment": al.report(), "start_girth": round(alpha0, 3), "start_repair": repair,
              "frames": int(moving + hold), "boundary_while_settling": len(part.boundary),
              "strain_mean": float(strain.mean()), "strain_p95": float(np.percentile(strain, 95)),
              "seam_gap_max_m": float(gaps.max()) if len(gaps) else 0.0}
    fitted = GarmentPart(np.arange(len(x)), x, garment.faces, part.boundary, rest, garment.seams)
    return fitted, report
