"""Scene flow from multi-view optical flow: where each garment vertex goes in the next frame.

The tracking stage (Sec. 3.1) refines each frame photometrically from a start, and its basin is
small: the per-face Gaussians at the fitting resolution (a 2-cm face is about one 128² pixel)
correct a start error of several millimetres, while a swinging hem moves centimetres between
frames. Dense optical flow between consecutive images of the same camera sees that
motion at the capture's full resolution, in the cloth's own texture, with a coarse-to-fine
search that covers tens of pixels. :class:`FlowPrediction` lifts it to 3D:

1. Visibility: the mesh of frame t-1 is z-buffered in every camera (:func:`zbuffer`); a vertex is
   seen where its depth is within ``depth_tolerance`` of the nearest surface.
2. Optical flow I_{t-1} -> I_t and back (OpenCV's DIS, Kroeger et al. 2016), per camera on the
   grey images; a vertex's observation is its projection moved by the forward flow, kept when the
   backward flow returns it within ``consistency_px`` (occlusions and disocclusions fail that test).
3. The displacements d of the solved vertices minimise

       sum_(i,c) rho(|pi_c(x_i + d_i) - p_ic|) (z_ic / f_c)^2  +  lambda sum_(i,j) in edges |d_i - d_j|^2,

   reprojection errors in metres at the vertex (pixels times depth over focal length), a Huber
   rho (``huber_px``), and a membrane smoothness over the mesh edges that carries the motion of
   seen vertices to unseen ones (a vertex seen by no camera moves with its neighbours). Vertices
   not solved (the body and the garment's boundary, placed by skinning) enter the smoothness term
   at their given positions. Gauss-Newton on the projections, re-weighted each iteration.
4. With ``collider_faces`` (the body), solved vertices within ``contact_range`` of it are paired
   with their closest collider point where the observations were made (frame t-1, or the current
   estimate, both outside the body), and a penalty kappa (n.(x - q) - margin)^2 on that point's
   plane, moved with the collider to where the caller put it, holds them outside. A garment vertex
   inside the body is hidden from every camera, so no later flow would bring it back.

docs/tracking.md measures the prediction against constant velocity on the demo capture.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ...camera import Camera
from .channels import (image_channels, opponent_channels, optical_flow, patterned_opponents,  # noqa: F401
                       scaled_flow, shading_free, texture_strength, to_gray8, to_rgb8)
from .raster import _in_front, projection_jacobian, rasterize, sample_bilinear, visible_vertices, zbuffer
from .silhouette import MaskOutline, silhouette_observation


@dataclass
class FlowObservation:
    """Where camera ``camera`` sees vertex ``vertex`` [N] in the next frame: pixel ``target`` [N, 2]."""

    camera: Camera
    vertex: np.ndarray
    target: np.ndarray

    def normal_equations(self, X: np.ndarray, huber_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertex [N], JᵀJ [N, 3, 3], Jᵀr [N, 3]) of the Huber-weighted reprojection errors at
        ``X`` [V, 3], in metres at the vertex (pixels times depth over focal length)."""
        uv, z, J = projection_jacobian(self.camera, X[self.vertex])
        r = uv - self.target
        nr = np.linalg.norm(r, axis=1)
        w = np.where(nr < huber_px, 1.0, huber_px / np.maximum(nr, 1e-12))
        s = (z / self.camera.K[0, 0])[:, None]  # pixels -> metres at the vertex
        Jm = J * s[:, :, None]
        rm = r * s
        return (self.vertex, np.einsum("nki,nkj->nij", Jm, Jm) * w[:, None, None],
                np.einsum("nki,nk->ni", Jm, rm) * w[:, None])


BEND_REFERENCES = ("rest", "start", "previous", "moved", "seen", "physics")  # FlowPrediction.bend_reference

class FlowPrediction:
    """Multi-view optical flow lifted to the vertices of a mesh (module docstring).

    Args:
        faces: [F, 3] the whole template (body and garment: the body occludes the garment).
        solve: [V] bool, the vertices to move (the free garment); the rest stay where the caller
            puts them and enter the smoothness term as fixed ends.
        smooth_faces: [F', 3] faces whose edges carry the smoothness term (the garment's).
        smoothness: lambda (dimensionless: an edge's difference of displacement [m] against a
            reprojection error at the vertex [m]).
        huber_px, consistency_px, depth_tolerance [m], iterations: see the module docstring.
        preset: DIS preset ("medium"; "fast" is ~3x cheaper and coarser).
        prior_weight: pull of the solved vertices toward their start. rest: [V, 3] the mesh whose
            edge lengths ``iso_weight`` holds (the template).
        bend_weight: weight of the bending term toward ``rest``: for each interior edge of
            ``smooth_faces``, the distance between the two vertices opposite it, toward its rest
            value. With the edge lengths held, that distance fixes the hinge's dihedral angle, so
            the term holds the template's folds (zero for the template and any rigid motion of it,
            as L_normal "rest") where the edge lengths alone let a fold slide along itself.
        bend_huber: [m] the bending term is quadratic up to this change of a hinge's distance and
            linear beyond (re-weighted each Gauss-Newton iteration; 0: quadratic everywhere), so
            the template's folds are held against small slides but a fold the garment really forms
            (a flared skirt swinging out) is not pulled back ever harder.
        bend_reference: what the bending term holds: "rest" the template's hinges, "start" those
            of the mesh each lift starts from (the previous frame for the prediction, the estimate
            for a correction): the garment's shape may change from the template's (a skirt that
            flares out bends without stretching) but not within one lift; "previous" as "start" in
            the prediction, and in :meth:`correct` the hinges of the tracked frame t-1; "moved"
            per hinge: the start's distance where it differs from the reference's (the template's)
            by more than ``bend_moved`` [m], the template's elsewhere (a fold the garment has made
            is kept, the template's shape holds where the garment still has it); "seen" as "moved",
            and only where both vertices opposite the hinge have flow observations in at least
            ``bend_views`` cameras in that lift (a fold the views see follows the data, an unseen
            hinge keeps the template's distance); "physics" the hinges the caller passes as ``bend_rest``
            (:class:`FlowStart`: those of the frame's physics step, the lift's reference under
            ``flow.carry`` "physics"; the template's without one), so the folds the simulator
            predicts are kept where the views do not resolve them (session 37).
        collider_faces: [Fc, 3] faces (over the same vertices, none solved) the solved vertices stay
            outside of, by ``collision_margin`` [m], penalty ``collision_weight``, for vertices
            within ``contact_range`` [m] of it (module docstring, 4). None: no collider.
    """

    def __init__(self, faces: np.ndarray, solve: np.ndarray, smooth_faces: np.ndarray, smoothness: float = 3.0,
                 huber_px: float = 1.5, consistency_px: float = 0.7, depth_tolerance: float = 5e-3,
                 iterations: int = 3, preset: str = "medium", prior_weight: float = 0.0,
                 rest: np.ndarray | None = None, iso_weight: float = 0.0, collider_faces: np.ndarray | None = None,
                 collision_margin: float = 5e-4, collision_weight: float = 1e3, contact_range: float = 0.03,
                 bend_weight: float = 0.0, bend_huber: float = 0.0, bend_reference: str = "rest",
                 bend_moved: float = 2e-3, bend_views: int = 2, min_texture: float = 0.0, highpass: float = 0.0,
                 texture_blur: float = 0.0):
        self.faces = np.asarray(faces, np.int64)
        self.solve = np.asarray(solve, bool)
        self.ids = np.flatnonzero(self.solve)
        self.pos = np.full(len(self.solve), -1, np.int64)
        self.pos[self.ids] = np.arange(len(self.ids))
        G, self._edges = _edge_difference(smooth_faces, self.solve)
        self._G_solve = G[:, self.ids]
        self._G_fixed = G[:, np.flatnonzero(~self.solve)]
        self._K = sp.kron((self._G_solve.T @ self._G_solve).tocsr(), sp.identity(3), format="csr")
        self.smoothness = smoothness
        self.huber_px = huber_px
        self.consistency_px = consistency_px
        self.depth_tolerance = depth_tolerance
        self.iterations = iterations
        self.preset = preset
        self.prior_weight = prior_weight
        self.iso_weight = iso_weight
        self.bend_weight = bend_weight
        self.bend_huber = bend_huber
        if bend_reference not in BEND_REFERENCES:
            raise ValueError(f"bend_reference must be one of {', '.join(BEND_REFERENCES)}, got {bend_reference!r}")
        self.bend_reference = bend_reference
        self.bend_moved = bend_moved
        self.bend_views = bend_views
        self._hinges = _hinge_pairs(smooth_faces, self.solve)
        self._rest_lengths = self._rest_hinges = None
        if rest is not None:
            R = np.asarray(rest, np.float64)
            self._rest_lengths = np.linalg.norm(R[self._edges[:, 0]] - R[self._edges[:, 1]], axis=1)
            self._rest_hinges = np.linalg.norm(R[self._hinges[:, 0]] - R[self._hinges[:, 1]], axis=1)
        self.collider_faces = None if collider_faces is None else np.asarray(collider_faces, np.int64)
        self.collision_margin = collision_margin
        self.collision_weight = collision_weight
        self.contact_range = contact_range
        self.min_texture = min_texture
        self.highpass = highpass
        self.texture_blur = texture_blur

    def observe(self, vertices: np.ndarray, cameras: list[Camera], images0: list[np.ndarray],
                images1: list[np.ndarray], channels: str = "luma",
                opponent: tuple[bool, bool] = (True, True)) -> list[FlowObservation]:
        """Flow observations of the solved vertices at ``vertices`` [V, 3] (frame t-1), from each
        camera's image pair (frame t-1, frame t; full resolution, sRGB [H, W, 3] or :func:`to_gray8`),
        on the luma or (``channels="colour"``, colour images) also the ``opponent`` channels."""
        obs = []
        for cam, a, b in zip(cameras, images0, images1):
            depth, face = zbuffer(vertices, self.faces, cam)
            if channels != "colour":
                a, b = to_gray8(a), to_gray8(b)
            obs.append(self._observation(vertices, cam, a, b, depth, face, None, self.preset, channels,
                                         opponent=opponent))
        return obs

    def _observation(self, vertices: np.ndarray, cam: Camera, g0: np.ndarray, g1: np.ndarray, depth: np.ndarray,
                     face: np.ndarray, valid: np.ndarray | None, preset: str, channels: str = "luma",
                     factor: int = 1, opponent: tuple[bool, bool] = (True, True)) -> FlowObservation:
        """The flow observations of the seen solved vertices from view ``g0`` to ``g1`` (grey uint8,
        or sRGB for ``channels="colour"``: one set of observations per channel, each checked
        forward-backward on its own), the flow computed at 1/``factor`` size (:func:`scaled_flow`)."""
        seen = visible_vertices(vertices, self.faces, cam, self.depth_tolerance, depth, face) & self.solve
        idx = np.flatnonzero(seen)
        uv = cam.project(vertices[idx])[0]
        if valid is not None:  # the synthetic view must hold texture around the vertex
            ok = sample_bilinear(valid[..., None].astype(np.float64), uv)[:, 0] > 0.999
            idx, uv = idx[ok], uv[ok]
        vs, ts = [], []
        for a, b in image_channels(g0, g1, channels, opponent):
            if self.highpass > 0:  # the flow of the texture, not of the shading
                a, b = shading_free(a, self.highpass), shading_free(b, self.highpass)
            fw = scaled_flow(a, b, preset, factor)
            bw = scaled_flow(b, a, preset, factor)
            f = sample_bilinear(fw, uv)
            back = sample_bilinear(bw, uv + f)
            ok = np.linalg.norm(f + back, axis=1) < self.consistency_px * factor
            if self.min_texture > 0:  # only where the source view has texture in both directions
                src = a if self.texture_blur <= 0 else _blurred(a, self.texture_blur)
                ok &= sample_bilinear(texture_strength(src)[..., None], uv)[:, 0] >= self.min_texture
            vs.append(idx[ok])
            ts.append(uv[ok] + f[ok])
        return FlowObservation(cam, np.concatenate(vs), np.concatenate(ts))

    def correct(self, vertices: np.ndarray, cameras: list[Camera], images: list[np.ndarray],
                reference: ReferenceAppearance, iterations: int = 2, smoothness: float = 1.0,
                prior_weight: float = 0.1, preset: str = "fine", iso_weight: float | None = None,
                bend_weight: float | None = None, masks: list[np.ndarray] | None = None,
                silhouette_weight: float = 0.0, channels: str = "luma", coarse: int = 0,
                opponent: tuple[bool, bool] = (True, True), bend_reference: str | None = None,
                previous: np.ndarray | None = None, physics: np.ndarray | None = None) -> np.ndarray:
        """[V, 3] the solved vertices of ``vertices`` (an estimate of frame t) corrected against
        frame t's images by model-based flow (module docstring): each iteration renders the mesh
        as the reference frame saw it (:class:`ReferenceAppearance`), measures the flow from that
        synthetic view to the real one per camera, and lifts it (``smoothness`` and
        ``prior_weight`` toward the estimate). Unlike frame-to-frame flow, the error does not
        accumulate: the texture is always the reference frame's.

        ``masks`` (frame t's masks of ``cameras``, full resolution) with ``silhouette_weight`` > 0
        add each camera's :class:`~.silhouette.SilhouetteObservation`: the estimate's outline
        pulled onto the mask's, which sees what an aliased or plain texture does not.

        ``channels="colour"`` (colour ``images`` and reference) measures the flow on the luma and
        the colour-opponent channels that ``opponent`` keeps (:func:`image_channels`,
        :func:`patterned_opponents`). ``coarse`` > 0 runs that many
        extra iterations first with the flow at half size (:func:`scaled_flow`): coarse to fine, so
        an error of several pixels, which the full-size flow of an aliased texture misses, is
        corrected before the fine iterations.

        ``bend_reference`` (None: the instance's) is what the bending term holds in these lifts:
        "rest", "start" (each lift's estimate) or "previous" (the hinges of ``previous`` [V, 3],
        the tracked frame t-1: a fold may change from frame to frame, not within a frame's lifts)
        or "physics" (the hinges of ``physics`` [V, 3], the frame's physics step; the template's
        where it is None)."""
        ref = self.bend_reference if bend_reference is None else bend_reference
        bend_rest = None
        if ref == "previous":
            if previous is None:
                raise ValueError("bend_reference 'previous' needs the previous frame's vertices")
            ref, bend_rest = "rest", self.hinge_lengths(previous)
        elif ref == "physics":
            ref, bend_rest = "rest", None if physics is None else self.hinge_lengths(physics)
        X = np.asarray(vertices, np.float64).copy()
        views = [im if channels == "colour" else to_gray8(im) for im in images]
        outlines = ([MaskOutline(cam, m) for cam, m in zip(cameras, masks)]
                    if masks is not None and silhouette_weight > 0 else None)
        for it in range(coarse + iterations):
            factor = 2 if it < coarse else 1
            obs: list = []
            for k, (cam, g1) in enumerate(zip(cameras, views)):
                synth, valid, depth, face = reference.render(X, cam, fill=g1)
                obs.append(self._observation(X, cam, synth, g1, depth, face, valid, preset, channels, factor,
                                               opponent))
                if outlines is not None:
                    seen = visible_vertices(X, self.faces, cam, self.depth_tolerance, depth, face)
                    obs.append(silhouette_observation(X, self.faces, self.solve, outlines[k], seen,
                                                      weight=silhouette_weight))
            X = self.lift(X, obs, smoothness=smoothness, prior_weight=prior_weight, iso_weight=iso_weight,
                          bend_weight=bend_weight, huber_px=self.huber_px * factor, bend_reference=ref,
                          bend_rest=bend_rest)
        return X

    def hinge_lengths(self, vertices: np.ndarray) -> np.ndarray:
        """[H] the distances across the interior edges (the bending term's hinges) at ``vertices``."""
        X = np.asarray(vertices, np.float64)
        return np.linalg.norm(X[self._hinges[:, 0]] - X[self._hinges[:, 1]], axis=1)

    def views_per_vertex(self, observations: list) -> np.ndarray:
        """[V] int: in how many cameras the :class:`FlowObservation` s of ``observations`` see
        each vertex (a camera's channels count once; other observations, the silhouette's, not)."""
        count = np.zeros(len(self.solve), np.int64)
        for o in observations:
            if isinstance(o, FlowObservation) and len(o.vertex):
                count[np.unique(o.vertex)] += 1
        return count

    def lift(self, vertices: np.ndarray, observations: list[FlowObservation], start: np.ndarray | None = None,
             smoothness: float | None = None, prior_weight: float | None = None,
             iso_weight: float | None = None, bend_weight: float | None = None,
             huber_px: float | None = None, bend_reference: str | None = None,
             bend_rest: np.ndarray | None = None) -> np.ndarray:
        """[V, 3] the vertices moved by the observations (module docstring, step 3).

        vertices: [V, 3] where the observations were made (frame t-1, or the current estimate of
        frame t for :meth:`correct`). start: [V, 3] where the vertices that are not solved go
        (e.g. skinned to frame t), and the solved ones' start and prior (default: ``vertices``).
        smoothness, prior_weight, iso_weight, bend_weight, huber_px, bend_reference ("rest",
        "start" or "moved"): override the instance's; bend_rest: [H] the hinge distances "rest" holds
        (default: the template's, :meth:`hinge_lengths`).
        """
        huber = self.huber_px if huber_px is None else huber_px
        lam = self.smoothness if smoothness is None else smoothness
        prior = self.prior_weight if prior_weight is None else prior_weight
        iso = (self.iso_weight if iso_weight is None else iso_weight) if self._rest_lengths is not None else 0.0
        bend = (self.bend_weight if bend_weight is None else bend_weight) if self._rest_lengths is not None else 0.0
        X0 = np.asarray(vertices, np.float64)
        X = X0.copy() if start is None else np.asarray(start, np.float64).copy()
        n = len(self.ids)
        d_prior = (X - X0)[self.ids]  # the start is also the prior of the solved vertices
        d_fixed = (X - X0)[~self.solve]
        rhs_smooth = -(self._G_solve.T @ (self._G_fixed @ d_fixed))  # [n, 3]
        rows = (np.arange(n)[:, None, None] * 3 + np.arange(3)[None, :, None]).repeat(3, 2)
        cols = (np.arange(n)[:, None, None] * 3 + np.arange(3)[None, None, :]).repeat(3, 1)
        contact = self._contacts(X0, X)
        rest_hinges = self._rest_hinges if bend_rest is None else bend_rest
        ref = self.bend_reference if bend_reference is None else bend_reference
        if ref in ("start", "previous") and bend > 0:
            rest_hinges = self.hinge_lengths(X0)
        elif ref == "moved" and bend > 0:  # the start's hinges where its fold left the reference's
            h0 = self.hinge_lengths(X0)
            rest_hinges = np.where(np.abs(h0 - rest_hinges) > self.bend_moved, h0, rest_hinges)
        elif ref == "seen" and bend > 0:  # the same, only where the lift's flow sees both ends
            h0 = self.hinge_lengths(X0)
            views = self.views_per_vertex(observations)
            seen = (views[self._hinges] >= self.bend_views).all(1)
            rest_hinges = np.where(seen & (np.abs(h0 - rest_hinges) > self.bend_moved), h0, rest_hinges)
        active = np.zeros(n, bool)
        for _ in range(self.iterations):
            A = np.zeros((n, 3, 3))
            b = np.zeros((n, 3))
            for o in observations:
                if len(o.vertex) == 0:
                    continue
                vertex, JtJ, Jtr = o.normal_equations(X, huber)
                p = self.pos[vertex]
                for i in range(3):
                    b[:, i] -= np.bincount(p, Jtr[:, i], n)
                    for j in range(3):
                        A[:, i, j] += np.bincount(p, JtJ[:, i, j], n)
            d_cur = (X - X0)[self.ids]
            # the data term is linear in the increment: A (d - d_cur) = b
            M = sp.csr_matrix((A.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n))
            M = M + lam * self._K + (prior + 1e-9) * sp.identity(3 * n, format="csr")
            rhs = ((b + np.einsum("nij,nj->ni", A, d_cur)).ravel() + lam * np.asarray(rhs_smooth).ravel()
                   + prior * d_prior.ravel())
            if iso > 0:
                # edge lengths toward the reference's, linearised: |D (d - d_cur) + (L - L0)|^2
                D, r = self._length_jacobian(X, self._edges, self._rest_lengths)
                M = M + iso * (D.T @ D)
                rhs = rhs + iso * (D.T @ (D @ d_cur.ravel() - r))
            if bend > 0 and len(self._hinges):
                # the same on the distances across the interior edges (the hinges' dihedral angles)
                D, r = self._length_jacobian(X, self._hinges, rest_hinges)
                if self.bend_huber > 0:
                    # Huber: a hinge whose distance has moved more than bend_huber from the rest's
                    # (a fold that formed or opened) is pulled back with a bounded force
                    sw = np.sqrt(np.minimum(1.0, self.bend_huber / np.maximum(np.abs(r), 1e-12)))
                    D, r = sp.diags(sw) @ D, sw * r
                M = M + bend * (D.T @ D)
                rhs = rhs + bend * (D.T @ (D @ d_cur.ravel() - r))
            if contact is not None:
                # the collider's planes at the pairs' closest points: kappa (n.(x - q) - margin)^2 on
                # the vertices inside (once inside within this solve, kept in the active set)
                near, q, nrm = contact
                r = np.einsum("ij,ij->i", X[self.ids[near]] - q, nrm) - self.collision_margin
                active[near] |= r < 0
                a = active[near]
                if a.any():
                    k = self.collision_weight
                    An = np.zeros((n, 3, 3))
                    bn = np.zeros((n, 3))
                    sel = np.flatnonzero(near)[a]
                    na = nrm[a]
                    An[sel] = k * na[:, :, None] * na[:, None, :]
                    bn[sel] = k * na * (np.einsum("ij,ij->i", na, d_cur[sel]) - r[a])[:, None]
                    M = M + sp.csr_matrix((An.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n))
                    rhs = rhs + bn.ravel()
            d = _spd_solve(M, rhs).reshape(n, 3)
            X[self.ids] = X0[self.ids] + d
        return X

    def _contacts(self, X0: np.ndarray, X: np.ndarray):
        """(near [n] bool, points [m, 3], outward normals [m, 3]): the solved vertices within
        ``contact_range`` of the collider at ``X0`` (where the observations were made: the previous
        frame, or the current estimate), paired with their closest collider point there; the point
        (same triangle, same barycentric coordinates) and its interpolated normal taken on the
        collider at ``X``. Pairing where the cloth was outside keeps a vertex that the start put
        deep into a limb on the side it came from (the closest point at ``X`` would be the far side)."""
        if self.collider_faces is None or self.collision_weight <= 0 or len(self.collider_faces) == 0:
            return None
        from ...geometry import MeshQuery, vertex_normals

        d, f, w, _ = MeshQuery(X0, self.collider_faces).closest(X0[self.ids], max_dist=self.contact_range)
        near = d < self.contact_range
        tri = self.collider_faces[f[near]]
        q = np.einsum("nk,nkd->nd", w[near], X[tri])
        nrm = np.einsum("nk,nkd->nd", w[near], vertex_normals(X, self.collider_faces)[tri])
        return near, q, nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)

    def _length_jacobian(self, X: np.ndarray, e: np.ndarray, rest_lengths: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
        """D [E, 3n]: d(|x_i - x_j|)/d(solved displacement) at ``X`` for the pairs ``e`` [E, 2];
        r [E]: length - ``rest_lengths``."""
        v = X[e[:, 0]] - X[e[:, 1]]
        L = np.linalg.norm(v, axis=1)
        u = v / np.maximum(L, 1e-12)[:, None]
        rows, cols, vals = [], [], []
        for end, sign in ((0, 1.0), (1, -1.0)):
            p = self.pos[e[:, end]]
            m = p >= 0
            for k in range(3):
                rows.append(np.flatnonzero(m))
                cols.append(3 * p[m] + k)
                vals.append(sign * u[m, k])
        D = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(len(e), 3 * len(self.ids)))
        return D, L - rest_lengths

    def __call__(self, vertices: np.ndarray, cameras: list[Camera], images0: list[np.ndarray],
                 images1: list[np.ndarray], start: np.ndarray | None = None) -> np.ndarray:
        """[V, 3] float64: :meth:`observe` at ``vertices`` then :meth:`lift` (see there)."""
        return self.lift(vertices, self.observe(np.asarray(vertices, np.float64), cameras, images0, images1), start)


class FlowStart:
    """The tracker's start of frame t for the solved vertices (``garment_prediction="flow"``):
    :class:`FlowPrediction` from the tracked frame t-1, then ``corrections`` model-based
    corrections against the reference (first) frame's texture.

    Args:
        flow: the lift. cameras: the training views. reference_vertices: [V, 3] the tracked first
        frame; reference_images: its views (sRGB or :func:`to_gray8`). corrections: per frame (0: prediction only).
    """

    def __init__(self, flow: FlowPrediction, cameras: list[Camera], reference_vertices: np.ndarray,
                 reference_images: list[np.ndarray], corrections: int = 2, final_corrections: int = 0,
                 correction: dict | None = None, coarse: int = 0, predict_colour: bool = False):
        self.flow, self.cameras, self.corrections = flow, list(cameras), corrections
        self.predict_colour = predict_colour
        self.coarse = coarse  # half-size corrections before the first full-size one (not in refine)
        self.final_corrections = final_corrections
        self.correction = dict(correction or {})
        self._previous: np.ndarray | None = None  # the tracked frame t-1 of the last call
        self._carried: np.ndarray | None = None  # the last call's lift reference (bend_reference "physics")
        colour = self.correction.get("channels", "luma") == "colour"
        if colour:  # only the opponent channels in which the garment shows a pattern (none: the luma alone)
            opponent = patterned_opponents(reference_vertices, flow.faces, flow.solve, cameras, reference_images)
            colour = any(opponent)
            self.correction.update(opponent=opponent, channels="colour" if colour else "luma")
        self.reference = (ReferenceAppearance(reference_vertices, flow.faces, cameras, reference_images, colour=colour)
                          if corrections > 0 or final_corrections > 0 else None)

    def __call__(self, previous: np.ndarray, previous_grey: list[np.ndarray], grey: list[np.ndarray],
                 start: np.ndarray, masks: list[np.ndarray] | None = None,
                 carried: np.ndarray | None = None) -> np.ndarray:
        """[V, 3] float64 start of frame t. previous: [V, 3] tracked frame t-1; previous_grey,
        grey: :func:`to_gray8` views of frames t-1 and t; start: [V, 3] the other vertices' start
        (and the prior of the solved ones); masks: frame t's masks for the corrections'
        silhouette term (``correction["silhouette_weight"]``); carried: [V, 3] frame t-1 moved
        with the body to t, what the lift's smoothness takes as no motion (None: ``previous``)."""
        pc = {}
        if self.predict_colour and self.correction.get("channels") == "colour":
            pc = {"channels": "colour", "opponent": self.correction["opponent"]}
        obs = self.flow.observe(np.asarray(previous, np.float64), self.cameras, previous_grey, grey, **pc)
        # bend_reference "physics": the hinges of the lift's reference (the frame's physics step)
        self._carried = None if carried is None else np.asarray(carried, np.float64)
        physics = self._carried is not None and self.flow.bend_reference == "physics"
        X = self.flow.lift(previous if carried is None else carried, obs, start,
                           bend_rest=self.flow.hinge_lengths(carried) if physics else None)
        self._previous = np.asarray(previous, np.float64)  # the corrections' bending may hold its hinges
        if self.corrections > 0:
            X = self.flow.correct(X, self.cameras, grey, self.reference, self.corrections, masks=masks,
                                  coarse=self.coarse, previous=self._previous, physics=self._carried,
                                  **self.correction)
        return X

    def refine(self, vertices: np.ndarray, grey: list[np.ndarray], masks: list[np.ndarray] | None = None) -> np.ndarray:
        """[V, 3] float64: ``final_corrections`` corrections of the solved vertices of frame t's
        fitted ``vertices`` [V, 3] against its views ``grey`` (:func:`to_gray8`) and ``masks``."""
        if self.final_corrections == 0:
            return np.asarray(vertices, np.float64)
        return self.flow.correct(vertices, self.cameras, grey, self.reference, self.final_corrections, masks=masks,
                                 previous=self._previous, physics=self._carried, **self.correction)


class ReferenceAppearance:
    """The mesh as the reference frame's cameras saw it: projective texturing of a deformed mesh.

    Every face takes its grey value from the reference camera that saw the most of it (visible
    pixel count in a z-buffer of the reference mesh). :meth:`render` rasterizes the deformed mesh
    in any camera and fetches, for each pixel, the reference image at the same surface point
    (same face, same barycentric coordinates) in the face's camera: what that camera would see if
    the cloth had moved but kept its reference shading. The flow from this synthetic view to the
    real image of frame t is the remaining error of the estimate in that camera, measured
    against a fixed texture, so corrections do not accumulate drift.

    Args:
        vertices: [V, 3] the reference mesh (the first tracked frame). faces: [F, 3].
        cameras, images: the reference frame's views (sRGB [H, W, 3] in [0, 1]).
        depth_tolerance: [m] a surface point counts as seen by its camera within this depth.
        colour: keep the reference views in colour (sRGB; for ``channels="colour"`` corrections)
            rather than as luma.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera], images: list[np.ndarray],
                 depth_tolerance: float = 5e-3, colour: bool = False):
        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.cameras = list(cameras)
        self.grey = [(to_rgb8(im) if colour else to_gray8(im)[..., None]).astype(np.float64) for im in images]
        self.depth_tolerance = depth_tolerance
        self.depth = []
        score = np.zeros((len(self.cameras), len(self.faces)))
        for k, cam in enumerate(self.cameras):
            depth, face = zbuffer(self.vertices, self.faces, cam)
            self.depth.append(depth)
            score[k] = np.bincount(face[face >= 0], minlength=len(self.faces))
        self.source = np.where(score.max(0) > 0, score.argmax(0), -1)

    def render(self, vertices: np.ndarray, camera: Camera, fill: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(view [H, W] uint8 (grey reference) or [H, W, 3] (colour reference), valid [H, W] bool,
        depth [H, W], face [H, W]) of the mesh at ``vertices`` in ``camera``: reference texture
        where a face covers the pixel and its source camera saw the point; ``fill`` (a view of the
        same kind, default 0) elsewhere; depth and face of :func:`rasterize`."""
        depth, face, bary = rasterize(vertices, self.faces, camera)
        C = self.grey[0].shape[-1]
        if fill is None:
            out = np.zeros((camera.height, camera.width, C))
        else:
            fill = to_gray8(fill) if C == 1 else (to_rgb8(fill) if np.ndim(fill) == 3 else np.repeat(fill[..., None], 3, -1))
            out = np.asarray(fill, np.float64).reshape(camera.height, camera.width, C).copy()
        valid = np.zeros((camera.height, camera.width), bool)
        pix = np.flatnonzero(face.ravel() >= 0)
        f = face.ravel()[pix]
        src = self.source[f]
        P = np.einsum("nk,nkd->nd", bary.reshape(-1, 3)[pix], self.vertices[self.faces[f]])
        flat = out.reshape(-1, C)
        for k, cam in enumerate(self.cameras):
            sel = np.flatnonzero(src == k)
            if len(sel) == 0:
                continue
            uv, z = cam.project(P[sel])
            H, W = self.depth[k].shape
            inside = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
            seen = inside & _in_front(uv, z, self.depth[k], self.depth_tolerance)[0]
            sel, uv = sel[seen], uv[seen]
            flat[pix[sel]] = sample_bilinear(self.grey[k], uv)
            valid.ravel()[pix[sel]] = True
        out = np.clip(np.rint(out), 0, 255).astype(np.uint8)
        return (out[..., 0] if C == 1 else out), valid, depth, face


def _blurred(image: np.ndarray, sigma: float) -> np.ndarray:
    """[H, W] float32: a uint8 channel blurred by a Gaussian of ``sigma`` px."""
    import cv2

    return cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), sigma)


def _edge_difference(faces: np.ndarray, solve: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """([E, V] the difference operator x_i - x_j, [E, 2] the edges) of the edges of ``faces`` that
    touch a solved vertex."""
    f = np.asarray(faces, np.int64)
    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1), axis=0)
    e = e[solve[e[:, 0]] | solve[e[:, 1]]]
    r = np.arange(len(e))
    return sp.csr_matrix((np.r_[np.ones(len(e)), -np.ones(len(e))], (np.r_[r, r], np.r_[e[:, 0], e[:, 1]])),
                         shape=(len(e), len(solve))), e


def _hinge_pairs(faces: np.ndarray, solve: np.ndarray) -> np.ndarray:
    """[H, 2] for each edge shared by exactly two of ``faces``, the two vertices opposite it (those
    pairs that touch a solved vertex)."""
    f = np.asarray(faces, np.int64)
    ends = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    opposite = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    _, inv, cnt = np.unique(np.sort(ends, 1), axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    inner = np.flatnonzero(cnt[inv] == 2)
    o = opposite[inner[np.argsort(inv[inner], kind="stable")]].reshape(-1, 2)
    return o[solve[o[:, 0]] | solve[o[:, 1]]]


def _spd_solve(M: sp.csr_matrix, rhs: np.ndarray) -> np.ndarray:
    """``M``^-1 ``rhs`` for a symmetric positive definite ``M``: SuperLU with a symmetric ordering
    and no pivoting (a Cholesky in effect), several times faster than spsolve's default column
    ordering once the bending term fills the matrix."""
    from scipy.sparse.linalg import splu

    lu = splu(M.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    return lu.solve(np.asarray(rhs, np.float64))
