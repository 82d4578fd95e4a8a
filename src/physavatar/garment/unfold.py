"""Attached (boundary) targets that do not fold: an as-rigid-as-possible fit where they cross.

Each boundary vertex rides its own body triangle (:func:`garment.attachment_positions`). Where
the skin under an attached patch folds (a shoulder strap over a shrugging shoulder: the skin
under the dress's straps went to 0.2–270 % of its rest area on the CMU clips before issue 24's
collar fix), the patch's own triangles, all of whose vertices are prescribed, turn over and pass
through each other. No solver can repair that: both sides are prescribed (sim.contact leaves
such pairs out), and the written frame intersects itself.

:func:`unfold_targets` finds the frames whose attached triangles alone intersect (ipctk's exact
test, as ``simulate`` checks written frames) and, in those frames, replaces the per-vertex ride
by an as-rigid-as-possible fit of the attached patch to it (Sorkine & Alexa 2007: local
rotations and a global sparse solve, with the ride as a soft data term): the patch keeps its
start shape up to local rotations while following the skin on average, as a strap slides over
the skin instead of crumpling with it. Around those frames the fit is blended in and out over
``ramp`` frames (the targets stay continuous in time); every other frame is kept bit for bit, so
a motion whose attached triangles never cross gets exactly the per-vertex ride. A frame whose
fit still crosses is fitted again with 4× the stiffness and a tenth of the normal weight (the
patch freer to leave the skin where the skin itself folds through), at most ``rounds`` times.
"""

from __future__ import annotations

import ipctk
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import factorized

STIFFNESS = 10.0  # ARAP weight against the data term (per edge spoke, both in m²): 10 = close to rigid locally
RAMP = 5  # frames over which the fit is blended in before and out after the frames that cross
NORMAL_WEIGHT = 100.0  # the data term along the body's normal: the patch slides over the skin, not off or into it
OUTSIDE = True  # each fitted vertex kept at least as far out along the body's normal as its ride
ITERATIONS = 20  # local-global iterations per frame (warm-started from the frame before)


def _patch(faces: np.ndarray, vertex_ids: np.ndarray, start: np.ndarray):
    """(groups [K] (rows sharing one start point, sewn ones, move as one), faces [Fb, 3] and edges
    [Eb, 2] of the attached patch in group indices (primitives whose vertices are all attached))."""
    ids = np.asarray(vertex_ids, np.int64)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    _, group = np.unique(np.asarray(start, np.float64), axis=0, return_inverse=True)
    group = group.ravel()
    if not len(F) or not len(ids):
        return group, np.zeros((0, 3), np.int64), np.zeros((0, 2), np.int64)
    remap = -np.ones(max(int(F.max()), int(ids.max())) + 1, np.int64)
    remap[ids] = group
    inb = remap[F] >= 0
    Fb = remap[F[inb.all(1)]]
    Fb = Fb[(Fb[:, 0] != Fb[:, 1]) & (Fb[:, 1] != Fb[:, 2]) & (Fb[:, 2] != Fb[:, 0])]
    E = np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    Eb = np.sort(remap[E[(remap[E] >= 0).all(1)]], axis=1)
    Eb = np.unique(Eb[Eb[:, 0] != Eb[:, 1]], axis=0)
    return group, Fb, Eb


class _ARAP:
    """As-rigid-as-possible fit of a patch (start positions X [G, 3], edges [E, 2]) to data
    points P [G, 3]: min Σ_i (y_i − p_i)ᵀ W_i (y_i − p_i) + λ Σ_i Σ_{j∈N(i)} |(y_i − y_j) − R_i (x_i − x_j)|²,
    W_i = I + (``normal_weight`` − 1) n_i n_iᵀ: held ``normal_weight`` times harder along the
    body's normal n_i than along the skin, so the patch slides over the skin to keep its shape
    instead of leaving (or entering) the body."""

    def __init__(self, X: np.ndarray, edges: np.ndarray, stiffness: float, normal_weight: float = 1.0):
        G = len(X)
        self.X, self.lam, self.wn = X, float(stiffness), float(normal_weight)
        self.i, self.j = np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]]  # directed spokes
        self.e = X[self.i] - X[self.j]  # [2E, 3] rest spokes
        A = sp.coo_matrix((np.ones(len(self.i)), (self.i, self.j)), (G, G)).tocsr()
        self.L = sp.kron((sp.diags(np.asarray(A.sum(1)).ravel()) - A) * (2.0 * self.lam), sp.identity(3)).tocsr()
        self.R = np.broadcast_to(np.eye(3), (G, 3, 3)).copy()

    def fit(self, P: np.ndarray, normals: np.ndarray | None = None, iterations: int = ITERATIONS,
            outside: bool | None = None) -> np.ndarray:
        G = len(P)
        outside = OUTSIDE if outside is None else outside
        W = np.broadcast_to(np.eye(3), (G, 3, 3)).copy()
        n = None
        if normals is not None:
            n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            W += (self.wn - 1.0) * np.einsum("ga,gb->gab", n, n)
        rows = np.repeat(np.arange(3 * G).reshape(G, 3), 3, axis=1).ravel()
        cols = np.tile(np.arange(3 * G).reshape(G, 3), (1, 3)).ravel()
        solve = factorized((self.L + sp.csr_matrix((W.ravel(), (rows, cols)), (3 * G, 3 * G))).tocsc())
        WP = np.einsum("gab,gb->ga", W, P)
        Y = P.copy()
        for _ in range(iterations):
            # global: (W + 2λL) y = W p + λ Σ_j (R_i + R_j) e_ij
            rhs = np.zeros((G, 3))
            np.add.at(rhs, self.i, np.einsum("kab,kb->ka", self.R[self.i] + self.R[self.j], self.e))
            Y = solve((WP + self.lam * rhs).ravel()).reshape(G, 3)
            if outside and n is not None:  # never deeper than the ride along the body's normal
                Y += np.maximum(((P - Y) * n).sum(1), 0.0)[:, None] * n
            # local: R_i = the rotation closest to Σ_j (y_i − y_j) e_ijᵀ
            S = np.zeros((G, 3, 3))
            np.add.at(S, self.i, np.einsum("ka,kb->kab", Y[self.i] - Y[self.j], self.e))
            U, _, Vt = np.linalg.svd(S)
            D = np.ones((G, 3))
            D[:, 2] = np.sign(np.linalg.det(U @ Vt))
            D[D == 0] = 1.0
            self.R = np.einsum("gab,gb,gbc->gac", U, D, Vt)
        return Y


def crossing_frames(targets: np.ndarray, faces: np.ndarray, vertex_ids: np.ndarray) -> list[int]:
    """Frames of ``targets`` [T, K, 3] in which the attached patch's own triangles (those of
    ``faces`` whose vertices are all in ``vertex_ids``) intersect each other (ipctk)."""
    T = np.asarray(targets, np.float64)
    group, Fb, Eb = _patch(faces, vertex_ids, T[0])
    if len(Fb) < 2:
        return []
    first = np.unique(group, return_index=True)[1]
    mesh = ipctk.CollisionMesh(T[0][first], Eb.astype(np.int32), Fb.astype(np.int32))
    return [t for t in range(len(T)) if ipctk.has_intersections(mesh, T[t][first])]


def unfold_targets(targets: np.ndarray, faces: np.ndarray, vertex_ids: np.ndarray, normals: np.ndarray | None = None,
                   stiffness: float = STIFFNESS, normal_weight: float = NORMAL_WEIGHT, ramp: int = RAMP, rounds: int = 8):
    """Attached targets [T, K, 3] (garment.attachment_positions, rows ``vertex_ids`` of the
    garment ``faces``; ``normals`` [T, K, 3]: the body's normal under each, e.g. its attachment
    triangle's) with the frames where the attached patch crosses itself replaced by an
    as-rigid-as-possible fit of the patch (its shape at frame 0) to them, blended in and out
    over ``ramp`` frames; other frames unchanged (bit for bit), frame 0 always. Returns (targets,
    report: frames that crossed, frames changed, largest change [m], frames that still cross)."""
    Vt = np.array(targets, dtype=np.float64)
    report = {"frames_crossing": [], "frames_changed": 0, "max_change_m": 0.0, "still_crossing": []}
    bad = crossing_frames(Vt, faces, vertex_ids)
    report["frames_crossing"] = bad
    bad = [t for t in bad if t > 0]  # frame 0 is where the garment starts: never changed
    if not bad:
        return Vt, report
    group, Fb, Eb = _patch(faces, vertex_ids, Vt[0])
    first = np.unique(group, return_index=True)[1]
    T = len(Vt)
    mesh = ipctk.CollisionMesh(Vt[0][first], Eb.astype(np.int32), Fb.astype(np.int32))
    out = Vt.copy()
    lam, fitted = float(stiffness), set(bad)
    for _ in range(max(1, rounds)):
        alpha = np.zeros(T)
        for b in fitted:  # 1 at a fitted frame, falling linearly to 0 over `ramp` frames each side
            alpha = np.maximum(alpha, np.clip(1.0 - np.abs(np.arange(T) - b) / (ramp + 1.0), 0.0, 1.0))
        alpha[0] = 0.0
        arap = _ARAP(Vt[0][first], Eb, lam, normal_weight)
        todo = np.flatnonzero(alpha > 0)
        out = Vt.copy()
        for t in todo:  # in time order: each frame's rotations start from the frame before
            P = Vt[t][first]
            n = None
            if normals is not None:
                n = np.zeros((len(first), 3))
                np.add.at(n, group, np.asarray(normals[t], np.float64))
            Y = arap.fit(P, n)
            out[t] = ((1.0 - alpha[t]) * P + alpha[t] * Y)[group]
        still = [int(t) for t in todo if ipctk.has_intersections(mesh, out[t][first])]
        if not still:
            break
        if any(alpha[t] == 1.0 for t in still):  # the fit itself crosses: stiffer
            lam *= 4.0
        fitted |= set(still)  # a blend of the ride and the fit crosses: fit it fully, the ramp moves out
    report["still_crossing"] = still
    changed = np.abs(out - Vt).max(axis=(1, 2))
    report["frames_changed"] = int(np.sum(changed > 0))
    report["max_change_m"] = float(changed.max())
    report["stiffness"] = lam
    return out, report
