"""benchmarks/prepare_garment_parts.py's measurements on meshes with known answers (session 33)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from physavatar.capture import Template  # noqa: E402
from prepare_garment_parts import (drop_profile, normal_noise, offset_out, onto_truth,  # noqa: E402
                                   strap_sections, taubin_rest)


def grid(nx, ny, origin, ex, ey):
    """A regular triangulated grid of nx × ny vertices: origin + i ex + j ey."""
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    V = np.asarray(origin) + i.reshape(-1, 1) * np.asarray(ex) + j.reshape(-1, 1) * np.asarray(ey)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return V.astype(np.float64), np.concatenate([np.c_[a, b, c], np.c_[a, c, d]])


def with_body(V, F, boundary=None):
    """A template of a one-triangle body (far away) and the garment (V, F)."""
    BV = np.array([[5.0, 5, 0], [5.1, 5, 0], [5, 5.1, 0]])
    lab = np.r_[np.zeros(3, np.int64), np.ones(len(V), np.int64)]
    b = np.r_[np.zeros(3, bool), np.zeros(len(V), bool) if boundary is None else boundary]
    return Template(np.vstack([BV, V]), np.vstack([[0, 1, 2], F + 3]), lab, b, None, None)


def test_strap_sections_of_a_tilted_strip_are_its_width():
    # a strap 4.8 cm wide (x 0.065 … 0.113) in front (y < 0), leaning back 30° from vertical
    lean = np.radians(30)
    V, F = grid(5, 13, (0.065, -0.15, 1.1), (0.012, 0, 0), (0, 0.025 * np.sin(lean), 0.025 * np.cos(lean)))
    s = strap_sections(with_body(V, F), heights=(1.22, 1.26))
    for z in ("1.22", "1.26"):
        assert abs(s[z]["right_front"] - 4.8) < 1e-6
        assert s[z]["left_front"] == s[z]["left_back"] == s[z]["right_back"] == 0.0


def test_offset_out_moves_a_sheet_along_its_normal_and_keeps_the_boundary():
    V, F = grid(6, 6, (0, 0, 1.0), (0.02, 0, 0), (0, 0.02, 0))
    b = np.zeros(len(V), bool)
    b[:6] = True
    t = with_body(V, F, b)
    W = offset_out(t, 3.0)[3:]
    moved = W - V
    assert np.allclose(moved[b], 0)
    assert np.allclose(np.abs(moved[~b, 2]), 0.003) and np.allclose(moved[~b, :2], 0)
    assert len(np.unique(np.sign(moved[~b, 2]))) == 1  # one side: the sheet's normal


def test_normal_noise_has_the_asked_mean_and_is_seeded():
    V, F = grid(20, 20, (0, 0, 1.0), (0.02, 0, 0), (0, 0.02, 0))
    b = np.zeros(len(V), bool)
    b[:20] = True
    t = with_body(V, F, b)
    for rounds in (0, 20):
        d = (normal_noise(t, 2.5, rounds) - t.vertices)[3:]
        assert np.allclose(d[b], 0) and np.allclose(d[:, :2], 0)
        assert abs(np.abs(d[~b, 2]).mean() - 2.5e-3) < 1e-12  # the free vertices' mean |offset|
        assert np.array_equal(normal_noise(t, 2.5, rounds, seed=0), normal_noise(t, 2.5, rounds, seed=0))


def test_taubin_rest_keeps_a_plane_and_narrows_a_strip():
    # a plane stays a plane (umbrella smoothing moves vertices within it), pinned vertices stay
    V, F = grid(8, 8, (0, 0, 1.0), (0.02, 0, 0), (0, 0.02, 0))
    b = np.zeros(len(V), bool)
    b[:8] = True
    t = with_body(V, F, b)
    R = taubin_rest(t)[3:]
    assert np.allclose(R[:, 2], 1.0) and np.allclose(R[b], V[b])
    # a strip two edges wide held at its top: its rest area shrinks (session 33: the straps' -20 %)
    S, G = grid(3, 12, (0, 0, 1.0), (0.02, 0, 0), (0, 0, 0.02))
    top = S[:, 2] > 1.0 + 0.2
    ts = with_body(S, G, top)
    Rs = taubin_rest(ts)[3:]

    def area(X):
        return 0.5 * np.linalg.norm(np.cross(X[G[:, 1]] - X[G[:, 0]], X[G[:, 2]] - X[G[:, 0]]), axis=1).sum()

    assert area(Rs) < 0.95 * area(S)


def test_onto_truth_moves_a_sheet_onto_the_true_one():
    V, F = grid(6, 6, (0, 0, 1.003), (0.02, 0, 0), (0, 0.02, 0))
    T, TF = grid(8, 8, (-0.02, -0.02, 1.0), (0.02, 0, 0), (0, 0.02, 0))
    b = np.zeros(len(V), bool)
    b[0] = True
    P = onto_truth(with_body(V, F, b), with_body(T, TF))[3:]
    assert np.allclose(P[~b, 2], 1.0, atol=1e-9) and np.allclose(P[:, :2], V[:, :2])
    assert np.allclose(P[b], V[b])


def test_drop_profile_of_a_uniform_fall():
    z = np.linspace(0.3, 1.4, 50)
    seq = np.zeros((10, 50, 3))
    seq[:, :, 2] = z[None] - 0.001 * np.arange(10)[:, None] ** 2
    d = drop_profile(seq, frame=8)
    assert d["all"] == -64.0 and all(v == -64.0 for v in d.values())


def test_taubin_rest_is_the_symmetric_neighbour_average_on_an_open_strip():
    # reference: λ/μ passes of x ← x + s (mean of the mesh neighbours − x), holds fixed. trimesh's own
    # equal-weight operator takes each open edge in one direction and differs here by millimetres
    S, G = grid(3, 12, (0, 0, 1.0), (0.02, 0, 0), (0, 0.003, 0.02))
    S[:, 1] += 0.004 * np.sin(7 * S[:, 2])  # not a plane
    top = S[:, 2] > 1.2
    nbr = [set() for _ in S]
    for a, b, c in G:
        for u, v in ((a, b), (b, c), (c, a)):
            nbr[u].add(v)
            nbr[v].add(u)
    X = S.copy()
    for _ in range(10):
        for s in (0.5, -0.53):
            mean = np.array([X[sorted(n)].mean(0) for n in nbr])
            X = np.where(top[:, None], X, X + s * (mean - X))
    R = taubin_rest(with_body(S, G, top))[3:]
    assert np.abs(R - X).max() < 1e-12
