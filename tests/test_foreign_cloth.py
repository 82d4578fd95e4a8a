"""The independent cloth simulator of benchmarks/physics_recovery.py (benchmarks/foreign_cloth.py),
held to analytic results: its ground truth is only worth something if it is right."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from foreign_cloth import (ForeignCloth, ForeignSettings, bridson_directions,  # noqa: E402
                           closest_points_on_triangles, hinge_angle)


def triangle_grid(nx, ny, edge=0.05):
    """An equilateral triangle lattice in the xy plane: vertices [N, 3], faces [F, 3]."""
    pts = [((i + 0.5 * (j % 2)) * edge, j * edge * math.sqrt(3) / 2, 0.0) for j in range(ny) for i in range(nx)]
    faces = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
            faces += [[a, b, d], [a, d, c]] if j % 2 else [[a, b, c], [b, d, c]]
    return np.array(pts), np.array(faces)


def test_bridson_modes_are_the_hinge_angle_gradient_and_sum_to_zero():
    X = np.random.default_rng(0).normal(size=(6, 4, 3))
    u, _, _ = bridson_directions(X)
    eps = 1e-6
    grad = np.zeros_like(X)
    for v in range(4):
        for d in range(3):
            Xp, Xm = X.copy(), X.copy()
            Xp[:, v, d] += eps
            Xm[:, v, d] -= eps
            grad[:, v, d] = (hinge_angle(Xp) - hinge_angle(Xm)) / (2 * eps)
    np.testing.assert_allclose(u, -grad, atol=1e-7 * np.abs(grad).max())
    np.testing.assert_allclose(u.sum(axis=1), 0.0, atol=1e-12)


def test_closest_point_on_triangle_matches_a_dense_search():
    rng = np.random.default_rng(1)
    P, A, B, C = (rng.normal(size=(40, 3)) for _ in range(4))
    cp, w = closest_points_on_triangles(P, A, B, C)
    s, t = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    keep = s + t <= 1
    for m in range(len(P)):
        q = A[m] + s[keep, None] * (B[m] - A[m]) + t[keep, None] * (C[m] - A[m])
        brute = np.min(np.linalg.norm(q - P[m], axis=1))
        d = np.linalg.norm(cp[m] - P[m])
        assert brute - 1e-3 <= d <= brute + 1e-12
    assert np.all(w >= -1e-12) and np.allclose(w.sum(axis=1), 1.0)


def test_spring_lattice_is_a_membrane_of_the_given_stiffness():
    """An equilateral spring lattice under a small uniaxial strain ε with the other direction held
    (plane strain) stores ½ C11 ε² per area, C11 = κs/(1 − ν²) with ν = 1/3."""
    X, F = triangle_grid(9, 9)
    ks = 120.0
    cloth = ForeignCloth(X, F, [], 0.2, ks, 1e-6)
    eps = 1e-4
    Y = X * np.array([1 + eps, 1.0, 1.0])
    stretch = np.linalg.norm(Y[cloth.edges[:, 1]] - Y[cloth.edges[:, 0]], axis=1) - cloth.rest_length
    energy = 0.5 * np.sum(cloth.k * stretch**2)
    area = np.sum(0.5 * np.linalg.norm(np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]]), axis=1))
    assert energy / area == pytest.approx(0.5 * ks / (1 - 1 / 9) * eps**2, rel=1e-3)


def test_free_fall_follows_gravity_and_a_hanging_cloth_settles_below_its_anchor():
    X, F = triangle_grid(5, 5)
    cloth = ForeignCloth(X, F, [], 0.15, 50.0, 1e-6, ForeignSettings(alpha=0.0, beta=0.0))
    T = 6
    out, sub = cloth.simulate(X, np.zeros((T, 0, 3)), fps=25.0)
    t = (T - 1) / 25.0
    drop = X[:, 2].mean() - out[-1][:, 2].mean()
    # symplectic Euler: ½ g t² (1 + 1/n) after n steps
    n = (T - 1) * sub
    assert drop == pytest.approx(0.5 * 9.81 * t**2 * (1 + 1 / n), rel=1e-9)
    np.testing.assert_allclose(out[-1] - out[-1].mean(0), X - X.mean(0), atol=1e-9)  # no deformation in free fall

    # a sheet held by its top row and damped hangs down and comes to rest
    Xv = X[:, [0, 2, 1]] * np.array([1, 1, -1])  # vertical sheet, top row at z = 0
    top = np.flatnonzero(np.isclose(Xv[:, 2], 0.0))
    cloth = ForeignCloth(Xv, F, top, 0.15, 50.0, 1e-6, ForeignSettings(alpha=5.0))
    out, _ = cloth.simulate(Xv, np.repeat(Xv[top][None], 40, 0))
    assert np.all(out[-1][top] == Xv[top])
    speed = np.abs(out[-1] - out[-2]).max() * 25.0
    assert speed < 2e-3  # at rest
    assert out[-1][:, 2].min() < Xv[:, 2].min()  # stretched down by its weight


def test_cloth_falling_on_a_body_stays_outside_it():
    X, F = triangle_grid(6, 6, edge=0.04)
    X = X - X.mean(0) + np.array([0, 0, 0.03])
    # a static "body": a large square slab top face at z = 0 (two triangles, normals up)
    body = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    bf = np.array([[0, 1, 2], [0, 2, 3]])
    T = 20
    cloth = ForeignCloth(X, F, [], 0.15, 50.0, 1e-6, ForeignSettings(thickness=2e-3))
    out, _ = cloth.simulate(X, np.zeros((T, 0, 3)), np.repeat(body[None], T, 0), bf)
    assert out[-1][:, 2].min() >= 2e-3 - 1e-9  # pushed to the thickness, never through
    assert out[-1][:, 2].max() < 2.5e-3  # lying on it
