"""Scene flow for tracking (physavatar.stages.track.flow): each part against an independent reference.

- rasterize: against a slow per-pixel ray cast (Moller-Trumbore), depth, face and barycentrics;
- optical_flow: recovers a known sub-pixel shift of a textured image;
- lift: recovers a known smooth motion from exact projections (no bias from the smoothness term);
- ReferenceAppearance + correct: on a procedurally textured cloth seen by 4 cameras, the
  model-based flow correction brings an estimate 8 mm off to within 1 mm of the truth;
- the lift's bending term: a folded sheet whose unseen half the edge lengths leave flat folds back
  to the rest's crease angle; a rigid motion of the folded rest is still recovered exactly.
"""

from __future__ import annotations

import numpy as np

from physavatar.camera import Camera, intrinsics, look_at, ring_rig
from physavatar.stages.track.flow import (FlowObservation, FlowPrediction, ReferenceAppearance, optical_flow,
                                          rasterize, sample_bilinear, visible_vertices)


def _grid(n: int, size: float, z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A square n x n vertex grid in the plane x-z (facing -y) centred at the origin, height ``z``."""
    s = np.linspace(-size / 2, size / 2, n)
    X, Z = np.meshgrid(s, s, indexing="xy")
    V = np.stack([X.ravel(), np.zeros(n * n), Z.ravel() + z], 1)
    F = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            F += [[a, b, e], [a, e, d]]
    return V, np.asarray(F, np.int64)


def _ray_cast(vertices, faces, cam: Camera):
    """Slow reference: per pixel centre, the nearest triangle hit by the camera ray."""
    H, W = cam.height, cam.width
    o = cam.center
    Kinv = np.linalg.inv(cam.K)
    R = cam.w2c[:3, :3]
    depth = np.full((H, W), np.inf)
    face = np.full((H, W), -1)
    bary = np.zeros((H, W, 3))
    for v in range(H):
        for u in range(W):
            dc = Kinv @ np.array([u, v, 1.0])  # camera-space direction with z = 1
            d = R.T @ dc
            for f, (a, b, c) in enumerate(faces):
                e1, e2 = vertices[b] - vertices[a], vertices[c] - vertices[a]
                p = np.cross(d, e2)
                det = e1 @ p
                if abs(det) < 1e-14:
                    continue
                s = o - vertices[a]
                l1 = (s @ p) / det
                q = np.cross(s, e1)
                l2 = (d @ q) / det
                t = (e2 @ q) / det  # camera depth, since d has unit camera z
                if l1 < 0 or l2 < 0 or l1 + l2 > 1 or t <= 0:
                    continue
                if t < depth[v, u]:
                    depth[v, u], face[v, u] = t, f
                    bary[v, u] = (1 - l1 - l2, l1, l2)
    return depth, face, bary


def test_rasterize_matches_ray_cast():
    rng = np.random.default_rng(0)
    V = rng.uniform(-0.3, 0.3, (12, 3))
    F = np.array([rng.choice(12, 3, replace=False) for _ in range(10)])
    cam = Camera("c", 40, 30, intrinsics(40, 30, 50.0), look_at([0.2, -1.0, 0.3], [0, 0, 0]))
    depth, face, bary = rasterize(V, F, cam)
    rd, rf, rb = _ray_cast(V, F, cam)
    hit = np.isfinite(rd)
    assert hit.sum() > 100
    # pixel centres exactly on a shared edge may go to either triangle; everything else agrees
    same = face == rf
    assert same.mean() > 0.98
    np.testing.assert_array_equal(np.isfinite(depth), hit)
    np.testing.assert_allclose(depth[hit], rd[hit], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(bary[same & hit], rb[same & hit], atol=1e-8)


def test_visible_vertices_of_a_sphere_face_the_camera():
    import trimesh

    s = trimesh.creation.icosphere(3, 0.3)
    V, F = np.asarray(s.vertices), np.asarray(s.faces)
    cam = Camera("c", 160, 160, intrinsics(160, 160, 40.0), look_at([0, -2.0, 0], [0, 0, 0]))
    seen = visible_vertices(V, F, cam, depth_tolerance=2e-3)
    to_cam = cam.center - V
    facing = np.einsum("ij,ij->i", V / 0.3, to_cam / np.linalg.norm(to_cam, axis=1, keepdims=True))
    assert seen[facing > 0.2].all()  # clearly facing: seen
    assert not seen[facing < -0.15].any()  # behind the silhouette (beyond one edge of it): hidden


def _texture(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A smooth multi-scale pattern in [0, 1] of two surface coordinates [m]."""
    return np.clip(0.5 + 0.2 * np.sin(90 * u + 3 * np.sin(60 * v)) + 0.15 * np.cos(130 * v - 40 * u)
                   + 0.1 * np.sin(210 * u + 170 * v), 0.0, 1.0)


def test_optical_flow_recovers_a_known_shift():
    H, W = 96, 128
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    shift = np.array([3.4, -2.25])  # x, y pixels
    a = _texture(x / 400, y / 400)
    b = _texture((x - shift[0]) / 400, (y - shift[1]) / 400)  # b(p + shift) = a(p)
    f = optical_flow(a, b, "medium")
    inner = f[16:-16, 16:-16].reshape(-1, 2)
    err = np.linalg.norm(inner - shift, axis=1)
    assert np.median(err) < 0.1, np.median(err)


def _rig():
    return ring_rig(4, 1.6, 0.1, [0, 0, 0], 192, 192, 30.0, start_deg=-120.0)[:2] + \
        ring_rig(4, 1.6, 0.1, [0, 0, 0], 192, 192, 30.0, start_deg=-60.0)[:1] + \
        [Camera("top", 192, 192, intrinsics(192, 192, 30.0), look_at([0.3, -1.4, 0.8], [0, 0, 0]))]


def _motion(V: np.ndarray) -> np.ndarray:
    """A smooth, non-rigid displacement of the grid [m]: a translation plus a bend."""
    d = np.zeros_like(V)
    d[:, 0] = 0.006
    d[:, 1] = -0.004 + 0.3 * V[:, 0] ** 2
    d[:, 2] = 0.003 * np.sin(V[:, 0] / 0.1)
    return d


def test_lift_recovers_a_known_motion_from_exact_projections():
    V, F = _grid(9, 0.4)
    cams = _rig()
    solve = np.ones(len(V), bool)
    d = _motion(V)
    obs = []
    for cam in cams:
        idx = np.flatnonzero(visible_vertices(V, F, cam))
        obs.append(FlowObservation(cam, idx, cam.project(V[idx] + d[idx])[0]))
    assert min(len(o.vertex) for o in obs) > 40
    # the bend is not in the smoothness term's null space: a weak smoothness leaves no bias
    lifted = FlowPrediction(F, solve, F, smoothness=1e-7, iterations=6).lift(V, obs)
    err = np.linalg.norm(lifted - (V + d), axis=1)
    assert err.max() < 1e-6, err.max()
    # the smoothness carries a vertex no camera sees with its neighbours: exactly, for a motion
    # affine in the rest position (the membrane term's interpolation on a symmetric grid)
    hidden = 40
    d = np.stack([0.006 + 0.05 * V[:, 0], -0.004 + 0.04 * V[:, 2], 0.003 + 0.02 * V[:, 0]], 1)
    obs2 = []
    for cam in cams:
        idx = np.flatnonzero(visible_vertices(V, F, cam))
        idx = idx[idx != hidden]
        obs2.append(FlowObservation(cam, idx, cam.project(V[idx] + d[idx])[0]))
    lifted = FlowPrediction(F, solve, F, smoothness=1e-3, iterations=6).lift(V, obs2)
    assert np.linalg.norm(lifted[hidden] - (V + d)[hidden]) < 1e-6


def _render(V: np.ndarray, F: np.ndarray, rest: np.ndarray, cam: Camera) -> np.ndarray:
    """[H, W, 3] a procedurally textured mesh (texture fixed to the rest surface) on grey."""
    depth, face, bary = rasterize(V, F, cam)
    img = np.full((cam.height, cam.width), 0.5)
    hit = face >= 0
    P = np.einsum("nk,nkd->nd", bary[hit], rest[F[face[hit]]])
    img[hit] = _texture(P[:, 0], P[:, 2])
    return np.repeat(img[..., None], 3, 2)


def test_model_based_correction_recovers_the_true_mesh():
    V0, F = _grid(21, 0.4)
    cams = _rig()
    truth = V0 + _motion(V0)
    ref = ReferenceAppearance(V0, F, cams, [_render(V0, F, V0, c) for c in cams])
    # the reference mesh seen by a reference camera: that camera's image where its faces are the
    # source, and another camera's view of the same surface point elsewhere (resampled)
    g, valid, _, face = ref.render(V0, cams[0])
    want = np.rint(_render(V0, F, V0, cams[0])[..., 0] * 255)
    own = valid & (ref.source[np.maximum(face, 0)] == 0)
    assert valid.mean() > 0.1 and own.sum() > 0.3 * valid.sum()
    assert np.abs(g[own].astype(float) - want[own]).max() <= 1.0
    assert np.median(np.abs(g[valid].astype(float) - want[valid])) <= 3.0
    images = [_render(truth, F, V0, c) for c in cams]
    solve = np.ones(len(V0), bool)
    start = V0 + np.array([0.0, 0.0, 0.008])  # 8+ mm off
    e0 = np.linalg.norm(start - truth, axis=1).mean()
    fp = FlowPrediction(F, solve, F)
    X = fp.correct(start, cams, images, ref, iterations=3, prior_weight=0.0)
    e1 = np.linalg.norm(X - truth, axis=1).mean()
    assert e0 > 8e-3
    assert e1 < 1e-3, (e0, e1)


def test_sample_bilinear_is_exact_on_affine_fields():
    H, W = 20, 30
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    field = np.stack([2 * x + 3 * y + 1, -x + 0.5 * y], -1)
    uv = np.random.default_rng(1).uniform([0, 0], [W - 1, H - 1], (50, 2))
    want = np.stack([2 * uv[:, 0] + 3 * uv[:, 1] + 1, -uv[:, 0] + 0.5 * uv[:, 1]], 1)
    np.testing.assert_allclose(sample_bilinear(field, uv), want, atol=1e-9)


def test_lift_keeps_cloth_on_the_side_of_the_collider_it_came_from():
    """Observations that drag a sheet 3 cm back through a 2 cm slab standing 5 mm behind it: with the
    collider the sheet stops in front of the slab (margin 0.5 mm, within the penalty's give); the
    contact pairs come from where the sheet was, so it is not pushed out through the far side."""
    import trimesh

    Vs, Fs = _grid(9, 0.4)
    box = trimesh.creation.box(extents=(0.6, 0.02, 0.6))
    Vb = np.asarray(box.vertices) + [0.0, 0.015, 0.0]  # y in [0.005, 0.025]; the sheet is at y = 0
    Fb = np.asarray(box.faces) + len(Vs)
    V = np.concatenate([Vs, Vb])
    F_all = np.concatenate([Fs, Fb])
    solve = np.r_[np.ones(len(Vs), bool), np.zeros(len(Vb), bool)]
    cams = _rig()
    obs = []
    for cam in cams:
        idx = np.flatnonzero(visible_vertices(Vs, Fs, cam))
        obs.append(FlowObservation(cam, idx, cam.project(Vs[idx] + [0.0, 0.03, 0.0])[0]))
    free = FlowPrediction(F_all, solve, Fs, smoothness=1e-3, iterations=4).lift(V, obs)
    np.testing.assert_allclose(free[:len(Vs), 1], 0.03, atol=1e-6)  # no collider: straight through
    held = FlowPrediction(F_all, solve, Fs, smoothness=1e-3, iterations=4, collider_faces=Fb,
                          collision_margin=5e-4).lift(V, obs)
    y = held[:len(Vs), 1]
    # in front of the slab's near face; the penalty (weight 1e3 against four cameras pulling 25 mm
    # further) gives a fraction of a millimetre of its 0.5 mm margin
    assert y.max() < 0.005 - 1e-4, y.max()
    assert y.min() > 0.0, y.min()  # and moved toward it, as the observations say
    np.testing.assert_array_equal(held[len(Vs):], Vb)


def _fold(V: np.ndarray, degrees: float) -> np.ndarray:
    """The grid of :func:`_grid` folded along its middle column (the line x = 0, along z): the half
    x > 0 turned by ``degrees`` toward -y. The crease runs along mesh edges, so every edge keeps its
    length: a fold is an isometry of the sheet."""
    a = np.radians(degrees)
    out = V.copy()
    r = V[:, 0] > 1e-9
    out[r, 0] = V[r, 0] * np.cos(a)
    out[r, 1] = -V[r, 0] * np.sin(a)
    return out


def test_hinge_pairs_are_the_vertices_opposite_each_interior_edge():
    from physavatar.stages.track.flow import _hinge_pairs

    F = np.array([[0, 1, 2], [2, 1, 3], [2, 3, 4]])  # interior edges 1-2 and 2-3
    got = {tuple(sorted(p)) for p in _hinge_pairs(F, np.ones(5, bool))}
    assert got == {(0, 3), (1, 4)}
    assert len(_hinge_pairs(F, np.array([True, False, False, False, False]))) == 1  # only pairs touching a solved vertex


def test_bending_holds_a_fold_the_edge_lengths_let_flatten():
    """A sheet folded 90 degrees along its middle (the rest shape), the left half seen by the cameras,
    the right half by none, started nearly flat (folded 10 degrees: every edge at its rest length).
    The edge-length term alone leaves the unseen half where it started; with the bending term the
    crease returns to the rest's 90 degrees. The sheet's flat hinges beyond it are held only to
    second order (the distance across a flat hinge is stationary in its angle), so the half curls
    by under a degree a hinge against the weak membrane term: within 11 mm of the rest at the far
    edge, 0.28 m for the start."""
    V0, F = _grid(9, 0.4)
    rest = _fold(V0, 90.0)
    start = _fold(V0, 10.0)
    left = np.flatnonzero(V0[:, 0] < 1e-9)  # the left half and the crease
    cams = _rig()
    obs = []
    for cam in cams:
        seen = np.intersect1d(np.flatnonzero(visible_vertices(start, F, cam)), left)
        obs.append(FlowObservation(cam, seen, cam.project(start[seen])[0]))
    assert len(np.unique(np.concatenate([o.vertex for o in obs]))) == len(left)
    solve = np.ones(len(V0), bool)
    kw = dict(smoothness=1e-6, iterations=20, rest=rest, iso_weight=10.0)
    flat = FlowPrediction(F, solve, F, **kw).lift(start, obs)
    np.testing.assert_allclose(flat, start, atol=1e-6)  # the edge lengths hold nothing here
    held = FlowPrediction(F, solve, F, bend_weight=10.0, **kw).lift(start, obs)
    np.testing.assert_allclose(held[left], start[left], atol=1e-5)  # the seen half stays as seen
    # the first column past the crease: at the rest's angle
    col = np.isclose(V0[:, 0], 0.05)
    angle = np.degrees(np.arctan2(-held[col, 1], held[col, 0]))
    np.testing.assert_allclose(angle, 90.0, atol=0.2)
    assert np.linalg.norm(start - rest, axis=1).max() > 0.25
    assert np.linalg.norm(held - rest, axis=1).max() < 0.011


def test_bending_term_leaves_a_rigid_motion_of_the_rest_unbiased():
    """The bending and edge-length terms are zero for the rest shape and any rigid motion of it: a
    folded sheet turned and moved is recovered exactly from exact projections."""
    V0, F = _grid(9, 0.4)
    rest = _fold(V0, 60.0)
    a = np.radians(8.0)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    truth = rest @ R.T + [0.01, -0.006, 0.004]
    obs = []
    for cam in _rig():
        idx = np.flatnonzero(visible_vertices(truth, F, cam))
        obs.append(FlowObservation(cam, idx, cam.project(truth[idx])[0]))
    lifted = FlowPrediction(F, np.ones(len(V0), bool), F, smoothness=1e-7, iterations=8, rest=rest,
                            iso_weight=10.0, bend_weight=10.0).lift(rest, obs)
    assert np.linalg.norm(lifted - truth, axis=1).max() < 1e-6


def test_huber_bending_lets_a_new_fold_form_and_leaves_small_changes_quadratic():
    """The rest is the flat sheet; the truth folds it 60 degrees along its middle (a fold the
    garment forms: the hinges across the crease change by centimetres), seen from four cameras
    with exact projections. A quadratic bending term 10x the data term pulls the crease open
    (11 mm off); the Huber form (quadratic up to 1 mm of hinge change, linear beyond) halves that. For a motion that changes no hinge by more than 1 mm the Huber
    form is the quadratic one, to the solver's precision."""
    V0, F = _grid(9, 0.4)
    truth = _fold(V0, 60.0)
    obs = []
    for cam in _rig():
        idx = np.flatnonzero(visible_vertices(truth, F, cam))
        obs.append(FlowObservation(cam, idx, cam.project(truth[idx])[0]))
    solve = np.ones(len(V0), bool)
    kw = dict(smoothness=1e-6, iterations=15, rest=V0, iso_weight=10.0, bend_weight=10.0)
    quad = FlowPrediction(F, solve, F, **kw).lift(V0, obs, start=_fold(V0, 50.0))
    hub = FlowPrediction(F, solve, F, bend_huber=1e-3, **kw).lift(V0, obs, start=_fold(V0, 50.0))
    e_quad = np.linalg.norm(quad - truth, axis=1).max()
    e_hub = np.linalg.norm(hub - truth, axis=1).max()
    assert e_quad > 0.008, e_quad
    assert e_hub < 0.6 * e_quad, (e_hub, e_quad)
    # small changes: a 10-degree fold (hinge distances change by 0.3 mm at most)
    small = _fold(V0, 10.0)
    obs = []
    for cam in _rig():
        idx = np.flatnonzero(visible_vertices(small, F, cam))
        obs.append(FlowObservation(cam, idx, cam.project(small[idx])[0]))
    kw["bend_weight"] = 1e3  # strong enough to hold the sheet visibly flatter than seen
    a = FlowPrediction(F, solve, F, **kw).lift(V0, obs)
    b = FlowPrediction(F, solve, F, bend_huber=1e-3, **kw).lift(V0, obs)
    assert np.abs(a - b).max() < 1e-9
    assert np.linalg.norm(a - small, axis=1).max() > 1e-4  # the term does act there
