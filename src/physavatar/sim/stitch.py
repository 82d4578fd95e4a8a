"""Seams: a stitch term that holds the vertices of two panels' shared seam together.

A garment made of separate sewing panels (the Berkeley Garment Library's panel files, any mesh
whose panels meet at coincident or listed vertices) is simulated panel by panel, each with its
own rest shape (the material-space panel); the seams are pairs (i, j) of cloth vertices that
must stay together. The term is a zero-rest-length spring per pair,

    E_stitch(x) = ½ k Σ_(i,j) w_ij ‖x_i − x_j‖²,

quadratic, so its Hessian is constant and positive semi-definite (exact = projected) and one
Newton step closes a seam exactly up to the other forces: the gap left by a force f pulling a
seam pair apart is f / (k w_ij). A layered seam (three or more panels meeting at one point) is
the same term with each extra vertex paired to the first. k is a penalty stiffness [N/m], not a
material parameter (``parameter`` None), and the term reads no step state: the sensitivity
pass differentiates through it unchanged.
"""

from __future__ import annotations

import numpy as np

from .terms import Blocks, Term

STITCH_STIFFNESS = 1e4  # N/m per seam pair: a 1 N pull (a dress's weight on a shoulder seam) opens 0.1 mm


class Stitch(Term):
    """½ k Σ w_ij ‖x_i − x_j‖² over seam pairs ``pairs`` [S, 2] (cloth vertex indices).

    Args:
        pairs: [S, 2] vertex index pairs to hold together.
        stiffness: k [N/m].
        weights: [S] per-pair weights (default 1).
    """

    def __init__(self, pairs, stiffness: float = STITCH_STIFFNESS, weights=None):
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if len(self.pairs) and np.any(self.pairs[:, 0] == self.pairs[:, 1]):
            raise ValueError("a stitch pair joins a vertex to itself")
        w = np.ones(len(self.pairs)) if weights is None else np.asarray(weights, dtype=np.float64)
        self.k = float(stiffness) * w  # [S]

    def _d(self, X):
        X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
        return X[self.pairs[:, 0]] - X[self.pairs[:, 1]], len(X)

    def energy(self, X) -> float:
        d, _ = self._d(X)
        return 0.5 * float(np.sum(self.k * np.einsum("sd,sd->s", d, d)))

    def gradient(self, X) -> np.ndarray:
        d, n = self._d(X)
        f = self.k[:, None] * d
        g = np.zeros((n, 3))
        np.add.at(g, self.pairs[:, 0], f)
        np.add.at(g, self.pairs[:, 1], -f)
        return g.ravel()

    def hessian(self, X, project=True) -> Blocks:
        eye = np.eye(3)
        K = np.block([[eye, -eye], [-eye, eye]])  # d²/dx² of ½‖x_i − x_j‖²: PSD, so projection is a no-op
        return Blocks(self.pairs, self.k[:, None, None] * K[None])


def seam_gaps(X, pairs) -> np.ndarray:
    """[S] distances across the seam pairs [S, 2] at positions X [N, 3] (m)."""
    X = np.asarray(X, dtype=np.float64)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return np.linalg.norm(X[pairs[:, 0]] - X[pairs[:, 1]], axis=1)
