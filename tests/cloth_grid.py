"""Simple meshes for simulator tests: a square cloth and an open tube; whether a cloth crosses a body."""

import ipctk
import numpy as np


def grid(n: int = 4, size: float = 1.0, z: float = 0.0, center: bool = False):
    """n×n vertices on a square of side ``size`` at height z (corner at the origin, or centred).

    Returns V [n², 3], F [2 (n−1)², 3] (the diagonal of each cell from (i, j+1) to (i+1, j)).
    """
    u = np.linspace(-size / 2, size / 2, n) if center else np.linspace(0.0, size, n)
    X, Y = np.meshgrid(u, u, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.full(n * n, z)], 1)
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [[a, a + n, a + 1], [a + 1, a + n, a + n + 1]]
    return V, np.array(F)


def tube(radius: float, z0: float, z1: float, n_around: int = 24, n_up: int = 6):
    """An open tube about the z axis: ``n_up`` rings of ``n_around`` vertices from z0 to z1,
    triangles facing outwards. Returns V [n_up·n_around, 3], F."""
    a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    V = np.array([[radius * np.cos(t), radius * np.sin(t), h] for h in np.linspace(z0, z1, n_up) for t in a])
    F = []
    for j in range(n_up - 1):
        for i in range(n_around):
            p, q = j * n_around + i, j * n_around + (i + 1) % n_around
            F += [[p, q, q + n_around], [p, q + n_around, p + n_around]]
    return V, np.array(F)


def body_crossings(x, F, B, Fb) -> bool:
    """ipctk's exact test on the cloth (x, F) and the body (B, Fb) as one mesh, body–body pairs
    left out (the body may intersect itself): True where the cloth crosses the body."""
    X = np.vstack([x, B])
    faces = np.vstack([F, Fb + len(x)])
    mesh = ipctk.CollisionMesh(X, ipctk.edges(faces), faces)
    mesh.can_collide = ipctk.make_static_obstacle_filter(len(x))
    return ipctk.has_intersections(mesh, X)
