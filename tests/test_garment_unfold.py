"""Attached targets that do not fold (garment.unfold_targets): a strip attached over a surface
that folds over itself crosses itself when each vertex rides its own triangle; the fit does not,
and frames where nothing crosses keep the ride bit for bit."""

import ipctk
import numpy as np

from physavatar.garment import attachment_normals, attachment_positions, make_attachment, unfold_targets
from physavatar.garment.unfold import crossing_frames


def _grid(u, v):
    """(vertices [nu·nv, 2] in (u, v), faces) of a regular grid."""
    U, W = np.meshgrid(u, v, indexing="ij")
    nu, nv = len(u), len(v)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return np.column_stack([U.ravel(), W.ravel()]), np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def _folding_surface(uv, s):
    """The surface at fold amount s ∈ [0, 1]: flat at 0; at 1 its middle runs back (x: u ↦ 0.8 − u
    on [0.4, 0.6]) and its far part dips through the near part (a pinch of skin folding over)."""
    u, v = uv[:, 0], uv[:, 1]
    g = np.where(u < 0.4, u, np.where(u < 0.6, 0.8 - u, u - 0.4))
    d = 0.05
    h = np.where(u < 0.4, 0.0, np.where(u < 0.6, d * (u - 0.4) / 0.2, d - 2 * d * (u - 0.6) / 0.2))
    return np.column_stack([(1 - s) * u + s * g, v, s * h])


def _strip():
    """A cloth strip, three rows, 3 mm above the flat surface: every vertex attached."""
    uv, F = _grid(np.linspace(0.1, 0.9, 33), np.linspace(0.06, 0.14, 3))
    return np.column_stack([uv, np.full(len(uv), 0.003)]), F


def test_a_strip_over_a_folding_surface_keeps_its_targets_from_crossing():
    suv, SF = _grid(np.linspace(0.0, 1.0, 41), np.linspace(0.0, 0.2, 5))
    T = 21
    bodies = np.stack([_folding_surface(suv, s) for s in np.r_[np.zeros(6), np.linspace(0, 1, T - 6)]])
    X, F = _strip()
    # a seam across the strip: its middle column's vertices doubled, the faces right of it on the
    # copies (sewn boundary vertices share one attachment point, garment_sim.sewn_points)
    col = np.arange(16 * 3, 17 * 3)
    Fs = F.copy()
    right = (F >= 17 * 3).any(1)
    Fs[right] = np.where(np.isin(F[right], col), F[right] - col[0] + len(X), F[right])
    Xs = np.vstack([X, X[col]])
    ids = np.arange(len(Xs))
    att = make_attachment(Xs, ids, bodies[0], SF, "s")
    ride = attachment_positions(att, bodies)
    np.testing.assert_allclose(ride[0], Xs, atol=1e-12)
    crossed = crossing_frames(ride, Fs, ids)
    assert crossed and crossed[-1] == T - 1  # the per-vertex ride crosses itself as the surface folds
    out, rep = unfold_targets(ride, Fs, ids, attachment_normals(att, bodies))
    assert rep["frames_crossing"] == crossed
    assert crossing_frames(out, Fs, ids) == [] and rep["still_crossing"] == []
    assert np.array_equal(out[:, len(X):], out[:, col])  # the seam stays closed, bit for bit
    # independent of crossing_frames: ipctk on the whole (welded) strip, every frame
    mesh = ipctk.CollisionMesh(X, ipctk.edges(F.astype(np.int32)), F.astype(np.int32))
    assert not any(ipctk.has_intersections(mesh, out[t, :len(X)]) for t in range(T))
    # frames where the surface is still flat (0-5) are the ride bit for bit; the crossing ones changed
    changed = np.flatnonzero(np.abs(out - ride).max(axis=(1, 2)) > 0)
    assert rep["frames_changed"] == len(changed) and changed.min() > 5 and set(crossed) <= set(changed)
    # the fit follows the surface on average: it moves less than half the strip's length (0.8 m)
    assert rep["max_change_m"] == np.abs(out - ride).max() and 0 < rep["max_change_m"] < 0.4

def test_targets_that_do_not_cross_are_returned_unchanged():
    suv, SF = _grid(np.linspace(0.0, 1.0, 21), np.linspace(0.0, 0.2, 5))
    bodies = np.stack([_folding_surface(suv, s) for s in np.linspace(0, 0.3, 5)])
    X, F = _strip()
    ids = np.arange(len(X))
    ride = attachment_positions(make_attachment(X, ids, bodies[0], SF, "s"), bodies)
    out, rep = unfold_targets(ride, F, ids)
    assert rep["frames_crossing"] == [] and rep["frames_changed"] == 0
    assert np.array_equal(out, ride)
