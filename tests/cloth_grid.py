"""A square cloth mesh for simulator tests."""

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
