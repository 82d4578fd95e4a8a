"""Simulation-ready garment templates fitted to an Anny body.

``make_garment(kind, body)`` drafts the garment's sewing pattern from the body's measurements
(``designs``), meshes and sews it (``pattern``, ``flatten``), pushes any vertex that is closer
to the body than the clearance outwards, selects the boundary (Dirichlet) vertices and attaches
them to the body surface. ``combine_template`` joins body and garments into the capture template.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..capture import Template
from ..files import atomic_path
from ..geometry import MeshQuery, adjacency, mesh_quality
from ..labels import LABEL_BODY, MAX_LABEL

MIN_CLEARANCE = 0.004  # m; every garment vertex at least this far from both body topologies
CCD_RESCALING = 0.9  # keep_clear's CCD stops at this fraction of the time of impact


@dataclass(frozen=True)
class Attachment:
    """Where each boundary vertex sits relative to the body surface.

    A vertex is the point at barycentric ``bary`` on body triangle ``triangles`` plus ``offset``
    expressed in that triangle's frame (first edge direction, in-plane perpendicular, face
    normal). For a vertex whose closest body point lies inside a triangle, the offset is purely
    along the normal; the frame makes the rest pose reproduce exactly in every case.

    Attributes:
        topology: Anny topology of the body mesh the triangles index.
        vertex_ids: [K] garment vertex indices.
        triangles: [K, 3] body vertex indices of each attachment triangle.
        bary: [K, 3]; offset: [K, 3] metres in the triangle frame.
    """

    topology: str
    vertex_ids: np.ndarray
    triangles: np.ndarray
    bary: np.ndarray
    offset: np.ndarray

    def __post_init__(self):
        K = len(self.vertex_ids)
        for name, shape in (("triangles", (K, 3)), ("bary", (K, 3)), ("offset", (K, 3))):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"attachment {name} must have shape {shape}, got {np.shape(getattr(self, name))}")


def _frames(tri: np.ndarray) -> np.ndarray:
    """[..., 3, 3] triangle frames (columns: edge direction, in-plane perpendicular, normal)."""
    e1 = tri[..., 1, :] - tri[..., 0, :]
    n = np.cross(e1, tri[..., 2, :] - tri[..., 0, :])
    e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return np.stack([e1, np.cross(n, e1), n], axis=-1)


def make_attachment(points: np.ndarray, vertex_ids: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray,
                    topology: str) -> Attachment:
    """Attach points [K, 3] to their closest points on the body mesh."""
    _, f, w, q = MeshQuery(body_vertices, body_faces).closest(points)
    tri_idx = body_faces[f]
    R = _frames(body_vertices[tri_idx])
    off = np.einsum("kji,kj->ki", R, points - q)  # R^T (p - q)
    return Attachment(topology, np.asarray(vertex_ids, np.int64), tri_idx, w, off)


def attachment_positions(attachment: Attachment, posed_body_vertices: np.ndarray) -> np.ndarray:
    """Positions [T, K, 3] of the attached vertices on a posed body [T, Vb, 3] (or [Vb, 3] -> [K, 3])."""
    Vb = np.asarray(posed_body_vertices, float)
    single = Vb.ndim == 2
    if single:
        Vb = Vb[None]
    tri = Vb[:, attachment.triangles]  # [T, K, 3, 3]
    q = np.einsum("kj,tkjd->tkd", attachment.bary, tri)
    out = q + np.einsum("tkij,kj->tki", _frames(tri), attachment.offset)
    return out[0] if single else out


def attachment_normals(attachment: Attachment, posed_body_vertices: np.ndarray) -> np.ndarray:
    """[T, K, 3] the unit normal of each attached vertex's body triangle on a posed body [T, Vb, 3]."""
    return _frames(np.asarray(posed_body_vertices, float)[:, attachment.triangles])[..., 2]


def keep_clear(attachment: Attachment, targets: np.ndarray, faces: np.ndarray, bodies: np.ndarray,
               body_faces: np.ndarray, clearance: float, rounds: int = 40):
    """Boundary targets [T, K, 3] (:func:`attachment_positions` on ``bodies`` [T, Vb, 3]) lifted
    off the body where the garment's boundary-only primitives would come too close to it.

    Each boundary vertex follows its own body triangle, so an edge (or triangle) of the garment
    whose vertices are all boundary vertices is a straight segment between points carried by
    *different* triangles. Where the body bends at the edges between those triangles (a
    shoulder folding as the arm swings), the segment sinks below the body surface: the
    prescribed motion itself crosses the body, and no solver can repair it (both sides are
    prescribed; IPC lets the body lag instead, and the frame crosses the body at its real pose).

    The floor is ``clearance`` or, when smaller, the least distance of those primitives to the
    body at frame 0 (frame 0, where the garment starts, is never changed). Frame after frame,
    the targets must be reachable from the last frame's along the straight path between frames
    (the simulator's sub-steps take them so, with or without skinned in-between bodies,
    body.between; the check is of the straight body path, not of the skinned one) without any of those
    primitives coming closer to the body than half the floor (half their start distance after a
    frame that failed; ipctk's exact CCD, Tight Inclusion), and end at least the floor away from it. A frame whose own targets pass is
    kept as it is (bit for bit); otherwise each boundary vertex keeps a lift along its
    triangle's normal (carried over from the last frame), raised by 1.25 × the shortfall of
    the primitives that are too close where the path stops or ends, until it passes (at most
    ``rounds`` times). Boundary vertices that share a target (sewn ones, attached at one point)
    share one lift, the largest any of them needs: lifted apart, their seam would open. Returns (targets [T, K, 3], report: floor, frames lifted, largest lift,
    frames that still failed).
    """
    import ipctk

    Vt = np.array(targets, dtype=np.float64)
    B = np.asarray(bodies, dtype=np.float64)
    ids = np.asarray(attachment.vertex_ids, np.int64)
    K, T = len(ids), len(Vt)
    report = {"floor_m": float(clearance), "frames_lifted": 0, "max_lift_m": 0.0, "failed_frames": []}
    F = np.asarray(faces, np.int64)
    if K < 2 or not len(F):
        return Vt, report
    remap = -np.ones(max(int(F.max()), int(ids.max())) + 1, np.int64)
    remap[ids] = np.arange(K)
    inb = remap >= 0
    E = np.unique(np.sort(np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    Eb, Fb = remap[E[inb[E].all(1)]], remap[F[inb[F].all(1)]]
    if not len(Eb):  # no boundary-only edge: a boundary vertex alone sits where its triangle puts it
        return Vt, report
    BF = np.asarray(body_faces, np.int64)
    mesh = ipctk.CollisionMesh(np.vstack([Vt[0], B[0]]), np.vstack([Eb, ipctk.edges(BF.astype(np.int32)) + K]),
                               np.vstack([Fb.reshape(-1, 3), BF + K]).astype(np.int32))
    mesh.can_collide = ipctk.make_vertex_patches_filter(np.r_[np.zeros(K), np.ones(len(B[0]))].astype(np.int32))
    # Tight Inclusion (exact, unlike the additive CCD's 90 % gap rule), to 0.1 mm: far faster
    # than its default 1 µm with a minimum distance, and a conservative answer when it stops early
    ccd = ipctk.TightInclusionCCD(1e-4, 10_000, CCD_RESCALING)

    def close(V, dist):
        """[(boundary rows, distance)] of the boundary-only primitives within ``dist`` of the body."""
        c = ipctk.NormalCollisions()
        c.build(mesh, V, dist)
        out = []
        for k in range(len(c)):
            vid = [i for i in c[k].vertex_ids(mesh.edges, mesh.faces) if i >= 0]
            out.append((np.array([i for i in vid if i < K]), np.sqrt(max(c[k].compute_distance(V[vid].ravel()), 0.0))))
        return out

    d0 = [d for _, d in close(np.vstack([Vt[0], B[0]]), clearance)]
    floor = min([clearance] + d0)
    report["floor_m"] = float(floor)
    if floor <= 0:
        return Vt, report
    need = floor * (1.0 - 1e-6)
    # boundary vertices that share a target (sewn boundary vertices share one attachment point,
    # garment_sim.sewn_points) share one lift: lifted apart, a seam would open by the lift
    _, group = np.unique(Vt[0], axis=0, return_inverse=True)
    group = group.ravel()
    lift = np.zeros(K)
    prev = np.vstack([Vt[0], B[0]])
    for t in range(1, T):
        normal = attachment_normals(attachment, B[t:t + 1])[0]  # [K, 3]
        # the path may come to half the floor; after a frame that failed, it starts closer than
        # that, and no lift of its end would let it pass (the CCD stops at once): half its start
        start = min([d for _, d in close(prev, need)], default=floor)
        path = 0.5 * (floor if start >= need else start)

        def shortfall(extra):
            """[K] how much further each boundary vertex must go out (0: the path and the end pass)."""
            V1 = np.vstack([Vt[t] + extra[:, None] * normal, B[t]])
            cand = ipctk.Candidates()
            cand.build(mesh, prev, V1, path)
            alpha = cand.compute_collision_free_stepsize(mesh, prev, V1, path, ccd)
            short = np.zeros(K)
            if alpha < 1.0:  # where the path reaches half the floor (the CCD stops 0.9 of the way there)
                at = prev + min(1.0, alpha / CCD_RESCALING) * (V1 - prev)
                for rows, d in close(at, 2.0 * floor):
                    short[rows] = np.maximum(short[rows], 1.25 * (floor - d) if d < need else 0.25 * floor)
            else:
                for rows, d in close(V1, need):
                    short[rows] = np.maximum(short[rows], 1.25 * (floor - d))
            most = np.zeros(K)
            np.maximum.at(most, group, short)
            return most[group]

        short = shortfall(np.zeros(K))
        if not short.any():
            lift[:] = 0.0
        else:
            for _ in range(rounds):
                lift += short
                short = shortfall(lift)
                if not short.any():
                    break
            else:
                report["failed_frames"].append(t)
            Vt[t] += lift[:, None] * normal
            report["frames_lifted"] += 1
            report["max_lift_m"] = max(report["max_lift_m"], float(lift.max()))
        prev = np.vstack([Vt[t], B[t]])
    return Vt, report


def garment_skinning_weights(garment_vertices: np.ndarray, body, garment_faces: np.ndarray | None = None,
                             iterations: int = 10, alpha: float = 0.5) -> np.ndarray:
    """Skinning weights [N, B] for garment vertices from the body's weights.

    Each vertex takes the body's weights interpolated (barycentric) at its closest body point;
    with ``garment_faces`` they are then smoothed over the garment mesh (``iterations`` Jacobi
    steps w <- (1 - alpha) w + alpha mean_neighbours(w)), so a loose skirt between the legs gets a
    blend of both legs rather than a tear where the closest leg changes. Rows are non-negative and
    sum to one.
    """
    P = np.asarray(garment_vertices, float)
    _, f, bary, _ = MeshQuery(body.rest_vertices, body.faces).closest(P)
    W = np.einsum("nk,nkb->nb", bary, body.skinning_weights[body.faces[f]])
    if garment_faces is not None and iterations > 0:
        A = adjacency(np.asarray(garment_faces), len(P))
        deg = np.asarray(A.sum(1)).ravel()
        deg[deg == 0] = 1.0
        for _ in range(iterations):
            W = (1 - alpha) * W + alpha * (A @ W) / deg[:, None]
    W = np.clip(W, 0.0, None)
    return W / W.sum(1, keepdims=True)


@dataclass(frozen=True)
class Garment:
    """A simulation-ready garment template (rest state, fitted to one body shape).

    Attributes:
        name: garment kind ("dress", "skirt", "tshirt").
        vertices: [N, 3] metres; faces: [F, 3] (outward-facing, manifold).
        face_uvs: [F, 3, 2] per-corner UVs from the sewing pattern, panels side by side in [0, 1]².
        boundary: [N] bool, Dirichlet vertices that follow the body.
        attachment: where the boundary vertices sit on the body.
        edge_length: target edge length (m) it was meshed at.
        clearance: minimum distance to the body (m) measured on both body topologies at build time.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    face_uvs: np.ndarray
    boundary: np.ndarray
    attachment: Attachment
    edge_length: float
    clearance: float = float("nan")

    def __post_init__(self):
        V, F = np.asarray(self.vertices), np.asarray(self.faces)
        if V.ndim != 2 or V.shape[1] != 3 or not np.isfinite(V).all():
            raise ValueError(f"garment {self.name}: vertices must be finite [N, 3], got {V.shape}")
        if F.ndim != 2 or F.shape[1] != 3 or F.min() < 0 or F.max() >= len(V):
            raise ValueError(f"garment {self.name}: faces must be [F, 3] indices into {len(V)} vertices")
        if np.shape(self.face_uvs) != (len(F), 3, 2):
            raise ValueError(f"garment {self.name}: face_uvs must be [{len(F)}, 3, 2], got {np.shape(self.face_uvs)}")
        if np.shape(self.boundary) != (len(V),) or not np.asarray(self.boundary).any():
            raise ValueError(f"garment {self.name}: boundary must be a non-empty [N] mask")
        if not np.array_equal(np.sort(self.attachment.vertex_ids), np.nonzero(self.boundary)[0]):
            raise ValueError(f"garment {self.name}: the attachment must cover exactly the boundary vertices")

    def quality(self) -> dict:
        """Mesh figures: min/max angle (deg), max/min area ratio, mean edge (m), counts, clearance (m)."""
        q = mesh_quality(np.asarray(self.vertices), np.asarray(self.faces))
        q["min_clearance_m"] = float(self.clearance)
        return q

    def save(self, path: str | Path) -> None:
        """Write an .npz (everything) or a .ply (mesh, boundary flag, UVs)."""
        path = Path(path)
        if path.suffix.lower() == ".ply":
            from ..files import PlyMesh, write_ply

            flags = {"boundary": self.boundary.astype(np.uint8)}
            write_ply(path, PlyMesh(self.vertices, self.faces, flags, self.face_uvs))
            return
        a = self.attachment
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, name=self.name, vertices=self.vertices, faces=self.faces, face_uvs=self.face_uvs,
                         boundary=self.boundary, edge_length=self.edge_length, clearance=self.clearance,
                         att_topology=a.topology, att_vertex_ids=a.vertex_ids, att_triangles=a.triangles,
                         att_bary=a.bary, att_offset=a.offset)

    @staticmethod
    def load(path: str | Path) -> "Garment":
        z = np.load(path, allow_pickle=False)
        att = Attachment(str(z["att_topology"]), z["att_vertex_ids"], z["att_triangles"], z["att_bary"],
                         z["att_offset"])
        return Garment(str(z["name"]), z["vertices"], z["faces"], z["face_uvs"], z["boundary"].astype(bool), att,
                       float(z["edge_length"]), float(z["clearance"]))


def _bodies(body):
    """The body of the given topology plus the full (rendered) and collider topologies of its shape."""
    from ..body.model import BodyModel

    out = {body.topology: body}
    for topo in ("full", "collider"):
        if topo not in out:
            out[topo] = BodyModel(body.shape, topology=topo)
    return out


def push_out(V: np.ndarray, F: np.ndarray, bodies: list[tuple[np.ndarray, np.ndarray]], clearance: float,
             iters: int = 30) -> tuple[np.ndarray, float]:
    """Make every garment vertex, and every body vertex against the garment surface, at least
    ``clearance`` apart: offending garment vertices move out along the body normal (their
    neighbours follow halfway, so the cloth stays smooth). Returns the new vertices and the
    smallest remaining distance."""
    from scipy.spatial import cKDTree

    V = V.copy()
    A = adjacency(F, len(V))
    queries = [MeshQuery(bv, bf) for bv, bf in bodies]
    for _ in range(iters):
        delta = np.zeros_like(V)
        worst = np.inf

        def propose(idx, d):
            cur = delta[idx]
            longer = np.linalg.norm(d, axis=1) > np.linalg.norm(cur, axis=1)
            delta[idx[longer]] = d[longer]

        for Q in queries:
            sd, q, n = Q.signed_distance(V, max_dist=2 * clearance)
            worst = min(worst, float(sd.min()))
            bad = np.nonzero(sd < clearance)[0]
            if len(bad):
                propose(bad, q[bad] + n[bad] * (clearance * 1.25) - V[bad])
            # body vertices near the garment surface: move the garment triangle they face
            near = np.isfinite(cKDTree(V).query(Q.V, distance_upper_bound=2 * clearance + 0.02)[0])
            if near.any():
                bi = np.nonzero(near)[0]
                d, f, w, q = MeshQuery(V, F).closest(Q.V[bi], max_dist=2 * clearance)
                worst = min(worst, float(d.min()))
                low = d < clearance
                for k in range(3):
                    vid = F[f[low], k]
                    push = Q.normals[bi[low]] * (1.25 * clearance - d[low])[:, None]
                    propose(vid, push)
        if worst >= clearance:
            return V, worst
        moved = (np.linalg.norm(delta, axis=1) > 0).astype(float)
        spread = (A @ delta) / np.maximum(A @ moved, 1.0)[:, None]
        V += np.where(moved[:, None] > 0, delta, 0.5 * spread)
    return V, worst


def push_clear(V: np.ndarray, F: np.ndarray, body_V: np.ndarray, body_F: np.ndarray, clearance: float,
               fixed=None) -> tuple[np.ndarray, int]:
    """A garment start the simulator can take: :func:`push_out` to ``clearance`` (``fixed``
    vertices, the boundary, put back), then the crossings a vertex-wise push cannot see (a body
    edge through a garment triangle whose corners are clear) by
    :func:`~physavatar.geometry.push_out_crossings`. Returns the vertices and the number of
    garment-body crossing pairs left (0: a valid start)."""
    from ..geometry import push_out_crossings

    moved, _ = push_out(V, F, [(body_V, body_F)], clearance)
    if fixed is not None:
        moved[fixed] = np.asarray(V)[fixed]
    return push_out_crossings(moved, F, body_V, body_F, clearance, fixed=fixed)


def body_clearance(V: np.ndarray, F: np.ndarray, body_V: np.ndarray, body_F: np.ndarray, reach: float = 0.02) -> float:
    """Smallest vertex-to-surface distance between garment and body, both ways (m): garment
    vertices to the body surface, and body vertices within ``reach`` of the garment to its surface."""
    from scipy.spatial import cKDTree

    d1 = MeshQuery(body_V, body_F).closest(V, max_dist=reach)[0].min()
    dv, _ = cKDTree(V).query(body_V, distance_upper_bound=reach)
    near = np.isfinite(dv)
    d2 = MeshQuery(V, F).closest(body_V[near], max_dist=reach)[0].min() if near.any() else np.inf
    return float(min(d1, d2))


def make_garment(kind: str, body, edge_length: float = 0.02, clearance: float = 0.008, seed: int = 0) -> "Garment":
    """Draft, mesh, sew and fit a garment to a rest body.

    Args:
        kind: one of ``GARMENTS``.
        body: ``BodyModel`` (any topology; the attachment refers to this one).
        edge_length: target edge length (m) in 3D.
        clearance: target gap between body and cloth (m) where the garment is fitted; loose parts
            get more. Every vertex ends at least ``MIN_CLEARANCE`` from both the full and the
            collider body.
        seed: seed of the body-surface sampling used to measure the body.
    """
    from .designs import DESIGNS, BodyMeasure
    from .pattern import sew

    if kind not in DESIGNS:
        raise ValueError(f"unknown garment {kind!r}; choose from {sorted(DESIGNS)}")
    if not 0.004 <= edge_length <= 0.1:
        raise ValueError(f"edge_length {edge_length} m is outside [0.004, 0.1]")
    bodies = _bodies(body)
    m = BodyMeasure.of(bodies["full"], seed=seed)
    design = DESIGNS[kind](m, edge_length, clearance)
    sm = sew(design.panels, edge_length, design.seam_lift)
    V, _ = push_out(sm.vertices, sm.faces, [(b.rest_vertices, b.faces) for b in (bodies["full"], bodies["collider"])],
                    max(MIN_CLEARANCE, 0.5 * clearance))
    cl = min(body_clearance(V, sm.faces, b.rest_vertices, b.faces) for b in (bodies["full"], bodies["collider"]))
    boundary = design.boundary(sm)
    ids = np.nonzero(boundary)[0]
    att = make_attachment(V[ids], ids, body.rest_vertices, body.faces, body.topology)
    return Garment(kind, V, sm.faces, sm.face_uvs, boundary, att, float(edge_length), cl)


def combine_template(body, body_vertices: np.ndarray | None, body_faces: np.ndarray | None,
                     garments: list[Garment]) -> Template:
    """Body and garments in one template mesh (label 0 body, 1.. garments in order).

    UV atlas: the body takes the left quarter (a cylindrical projection about the vertical axis),
    the garments share the rest in equal vertical slots, each keeping its own panel layout.
    """
    if body_vertices is None:
        body_vertices, body_faces = body.rest_vertices, body.faces
    if len(garments) > MAX_LABEL:
        raise ValueError(f"at most {MAX_LABEL} garments fit in a template")
    BV, BF = np.asarray(body_vertices, float), np.asarray(body_faces, np.int64)
    verts, faces, labels, bnd, uvs = [BV], [BF], [np.full(len(BV), LABEL_BODY)], [np.zeros(len(BV), bool)], []
    # body UVs: angle around the vertical axis through the body's centre, height; per corner,
    # unwrapped so a face never spans the seam at the back
    c = BV.mean(0)
    ang = np.arctan2(BV[:, 0] - c[0], -(BV[:, 1] - c[1])) / (2 * np.pi) + 0.5  # 0.5 at the front
    h = (BV[:, 2] - BV[:, 2].min()) / np.ptp(BV[:, 2])
    cu = ang[BF]
    cu = np.where(cu - cu[:, :1] > 0.5, cu - 1, np.where(cu - cu[:, :1] < -0.5, cu + 1, cu))
    cu = np.clip(cu, 0.0, 1.0)
    uvs.append(np.stack([0.24 * cu + 0.005, h[BF]], -1))
    n = len(BV)
    slot = 1.0 / max(len(garments), 1)
    for i, g in enumerate(garments):
        verts.append(g.vertices)
        faces.append(g.faces + n)
        labels.append(np.full(len(g.vertices), i + 1))
        bnd.append(np.asarray(g.boundary, bool))
        uv = np.asarray(g.face_uvs, float)
        uvs.append(np.stack([0.25 + 0.75 * uv[..., 0], i * slot + slot * uv[..., 1]], -1))
        n += len(g.vertices)
    return Template(np.concatenate(verts), np.concatenate(faces), np.concatenate(labels).astype(np.int64),
                    np.concatenate(bnd), np.concatenate(uvs))


def _garments():
    from .designs import DESIGNS

    return dict(DESIGNS)


GARMENTS = _garments()  # kind -> pattern drafting function (designs.py)
