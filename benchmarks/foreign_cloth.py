"""An independent cloth simulator: the "unseen simulator" of benchmarks/physics_recovery.py.

The issue behind the material estimator will be checked on garment motion made by a simulator the
project has not seen. The benchmark's other settings make their ground truth with physavatar.sim
itself (other steps, integrator, membrane law); this module is a stand-in for the unseen one,
written without any of physavatar.sim: its own discretisation of the same fabric parameters
(ρ [kg/m²], κs [N/m], κb [N·m]), as a typical explicit cloth code does it.

- Membrane: a mass-spring network, one linear spring per mesh edge with k_e = κs A_e / ℓ_e²
  (A_e: rest area of the triangles on the edge, ℓ_e its rest length). An equilateral lattice of
  such springs is an isotropic membrane with E·t = κs and ν = 1/3 (e.g. Lloyd et al. 2007), so
  the fabric's own ν is lost: model error, as in any mass-spring code.
- Bending: the hinge forces of Bridson, Marino & Fedkiw 2003 ("Simulation of clothing with folds
  and wrinkles"): F_i = k |E|²/(|N1| + |N2|) (sin(θ/2) − sin(θ̄/2)) u_i, with k = 4 κb so that at
  small angles the hinge stores (κb/2) k² per unit area on a cylinder (the flexural rigidity D).
- Damping: mass-proportional α [1/s] (air) and axial dashpots on the springs, c_e = β k_e.
- Time: symplectic (semi-implicit) Euler at a step below the springs' stability limit (tens of
  steps per frame), body and boundary interpolated linearly within a frame.
- Collision: closest point on the body's triangles; a vertex closer than the thickness δ is put
  back at δ along the face normal, its velocity relative to the body loses its inward normal part
  and Coulomb friction μ takes off tangential speed in proportion (velocity-level, inelastic).
- Lumped masses ρ A/3 per triangle corner.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.spatial import cKDTree


@dataclasses.dataclass(frozen=True)
class ForeignSettings:
    """α [1/s] mass damping; β [s] spring dashpots (c = β k); δ [m] collision thickness; μ friction;
    safety: the step is ``safety`` × the explicit stability limit 2/ω_max; gravity [m/s²] (z up)."""

    alpha: float = 0.2
    beta: float = 2e-4
    thickness: float = 2e-3
    friction: float = 0.2
    safety: float = 0.4
    gravity: tuple = (0.0, 0.0, -9.81)
    candidates: int = 12  # body triangles tested per vertex (nearest centroids)


def _edges_and_hinges(faces: np.ndarray):
    """Unique edges [E, 2], the triangles on each edge, and hinges [H, 4] (edge a, b; wings p, q)."""
    f = np.asarray(faces, dtype=np.int64)
    half = np.concatenate([f[:, [0, 1, 2]], f[:, [1, 2, 0]], f[:, [2, 0, 1]]])  # (a, b, opposite)
    key = np.sort(half[:, :2], axis=1)
    tri = np.tile(np.arange(len(f)), 3)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, half, tri = key[order], half[order], tri[order]
    first = np.r_[True, np.any(key[1:] != key[:-1], axis=1)]
    edges = key[first]
    group = np.cumsum(first) - 1
    counts = np.bincount(group)
    starts = np.flatnonzero(first)
    # the triangles of each edge (one or two)
    t0 = tri[starts]
    t1 = np.where(counts == 2, tri[np.minimum(starts + 1, len(tri) - 1)], -1)
    two = np.flatnonzero(counts == 2)
    s = starts[two]
    hinges = np.stack([half[s, 0], half[s, 1], half[s, 2], half[s + 1, 2]], axis=1)
    return edges, np.stack([t0, t1], axis=1), hinges


def hinge_angle(X: np.ndarray) -> np.ndarray:
    """Signed angle θ [H] between the two triangles of hinges X [H, 4, 3] (edge a, b; wings p, q);
    0 when flat."""
    a, b, p, q = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    e = b - a
    n1 = np.cross(p - a, p - b)
    n2 = np.cross(q - b, q - a)
    n1 = n1 / np.linalg.norm(n1, axis=1)[:, None]
    n2 = n2 / np.linalg.norm(n2, axis=1)[:, None]
    e_hat = e / np.linalg.norm(e, axis=1)[:, None]
    return np.arctan2(np.sum(np.cross(n1, n2) * e_hat, axis=1), np.sum(n1 * n2, axis=1))


def bridson_directions(X: np.ndarray):
    """Bridson et al.'s bending modes u [H, 4, 3] of hinges X (edge a, b; wings p, q), the
    normal-area sum |N1| + |N2| [H] and |E|² [H]. The u's sum to zero (no net force or torque)."""
    a, b, p, q = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    E = b - a
    lE = np.linalg.norm(E, axis=1)
    N1 = np.cross(p - a, p - b)
    N2 = np.cross(q - b, q - a)
    s1 = np.sum(N1 * N1, axis=1)
    s2 = np.sum(N2 * N2, axis=1)
    n1 = N1 / s1[:, None]
    n2 = N2 / s2[:, None]
    up = lE[:, None] * n1
    uq = lE[:, None] * n2
    ua = (np.sum((p - b) * E, axis=1) / lE)[:, None] * n1 + (np.sum((q - b) * E, axis=1) / lE)[:, None] * n2
    ub = -(np.sum((p - a) * E, axis=1) / lE)[:, None] * n1 - (np.sum((q - a) * E, axis=1) / lE)[:, None] * n2
    return np.stack([ua, ub, up, uq], axis=1), np.sqrt(s1) + np.sqrt(s2), lE**2


def closest_points_on_triangles(P, A, B, C):
    """Closest point on triangle (A, B, C) to P, all [M, 3] (Ericson, Real-Time Collision
    Detection 5.1.5), and its barycentric weights [M, 3]."""
    ab, ac, ap = B - A, C - A, P - A
    d1, d2 = np.sum(ab * ap, 1), np.sum(ac * ap, 1)
    bp = P - B
    d3, d4 = np.sum(ab * bp, 1), np.sum(ac * bp, 1)
    cp = P - C
    d5, d6 = np.sum(ab * cp, 1), np.sum(ac * cp, 1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    w = np.zeros((len(P), 3))
    done = np.zeros(len(P), dtype=bool)

    def put(mask, wa, wb, wc):
        m = mask & ~done
        w[m, 0], w[m, 1], w[m, 2] = wa[m], wb[m], wc[m]
        done[m] = True

    one, zero = np.ones(len(P)), np.zeros(len(P))
    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), one, zero, zero)  # vertex A
        put((d3 >= 0) & (d4 <= d3), zero, one, zero)  # vertex B
        t = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t, t, zero)  # edge AB
        put((d6 >= 0) & (d5 <= d6), zero, zero, one)  # vertex C
        t = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t, zero, t)  # edge AC
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), zero, 1 - t, t)  # edge BC
        denom = va + vb + vc
        v, ww = vb / denom, vc / denom
        put(np.ones(len(P), dtype=bool), 1 - v - ww, v, ww)  # interior
    return w[:, :1] * A + w[:, 1:2] * B + w[:, 2:] * C, w


class ForeignCloth:
    """The explicit mass-spring cloth of this module on one garment mesh."""

    def __init__(self, rest: np.ndarray, faces: np.ndarray, boundary: np.ndarray,
                 density: float, stretch_stiffness: float, bend_stiffness: float,
                 settings: ForeignSettings = ForeignSettings()):
        self.rest = np.asarray(rest, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.s = settings
        n = len(self.rest)
        self.free = np.ones(n, dtype=bool)
        self.free[np.asarray(boundary, dtype=np.int64)] = False
        self.boundary = np.flatnonzero(~self.free)
        X = self.rest
        tri_area = 0.5 * np.linalg.norm(np.cross(X[self.faces[:, 1]] - X[self.faces[:, 0]],
                                                 X[self.faces[:, 2]] - X[self.faces[:, 0]]), axis=1)
        self.mass = np.bincount(self.faces.ravel(), np.repeat(tri_area / 3.0, 3), minlength=n) * density
        self.edges, edge_tris, self.hinges = _edges_and_hinges(self.faces)
        self.rest_length = np.linalg.norm(X[self.edges[:, 1]] - X[self.edges[:, 0]], axis=1)
        edge_area = tri_area[edge_tris[:, 0]] + np.where(edge_tris[:, 1] >= 0, tri_area[edge_tris[:, 1]], 0.0)
        self.k = stretch_stiffness * edge_area / self.rest_length**2
        self.c = settings.beta * self.k
        self.kb = 4.0 * bend_stiffness
        self.rest_half_sin = np.sin(0.5 * hinge_angle(X[self.hinges]))
        # explicit stability: ω_max² ≤ max_i Σ_j k_ij (1/m_i + 1/√(m_i m_j)) (Gershgorin on M^-½ K M^-½)
        i, j = self.edges[:, 0], self.edges[:, 1]
        cross = self.k / np.sqrt(self.mass[i] * self.mass[j])
        row = (np.bincount(self.edges.ravel(), np.repeat(self.k, 2), minlength=n) / self.mass
               + np.bincount(self.edges.ravel(), np.repeat(cross, 2), minlength=n))
        w2 = float(np.max(row[self.free])) if self.free.any() else 1.0
        self.max_step = settings.safety * 2.0 / math.sqrt(w2)

    def forces(self, x, v):
        """Total force [N, 3] (gravity, springs, dashpots, bending, air damping)."""
        m = self.mass[:, None]
        f = m * np.asarray(self.s.gravity) - self.s.alpha * m * v
        i, j = self.edges[:, 0], self.edges[:, 1]
        d = x[j] - x[i]
        length = np.linalg.norm(d, axis=1)
        dh = d / length[:, None]
        axial = self.k * (length - self.rest_length) + self.c * np.sum((v[j] - v[i]) * dh, axis=1)
        fe = axial[:, None] * dh
        np.add.at(f, i, fe)
        np.add.at(f, j, -fe)
        if len(self.hinges):
            H = x[self.hinges]
            u, nsum, e2 = bridson_directions(H)
            half_sin = np.sin(0.5 * hinge_angle(H))
            mag = self.kb * e2 / nsum * (half_sin - self.rest_half_sin)
            np.add.at(f, self.hinges.ravel(), (mag[:, None, None] * u).reshape(-1, 3))  # u = −∂θ/∂x
        return f

    def collide(self, x, v, body, body_velocity, body_faces, tree):
        """Project vertices within the thickness of the body back out (positions and velocities)."""
        s = self.s
        k = min(s.candidates, len(body_faces))
        _, cand = tree.query(x, k=k)
        cand = cand.reshape(len(x), k)
        P = np.repeat(x, k, axis=0)
        tri = body_faces[cand.ravel()]
        A, B, C = body[tri[:, 0]], body[tri[:, 1]], body[tri[:, 2]]
        cp, w = closest_points_on_triangles(P, A, B, C)
        dist = np.linalg.norm(P - cp, axis=1).reshape(len(x), k)
        best = np.argmin(dist, axis=1)
        pick = np.arange(len(x)) * k + best
        cp, w, tri = cp[pick], w[pick], tri[pick]
        nrm = np.cross(body[tri[:, 1]] - body[tri[:, 0]], body[tri[:, 2]] - body[tri[:, 0]])
        nrm /= np.linalg.norm(nrm, axis=1)[:, None]
        phi = np.sum((x - cp) * nrm, axis=1)
        hit = self.free & (phi < s.thickness) & (dist[np.arange(len(x)), best] < 0.05)
        if not hit.any():
            return x, v, 0
        x = x.copy()
        v = v.copy()
        x[hit] += (s.thickness - phi[hit])[:, None] * nrm[hit]
        vb = np.einsum("mk,mkd->md", w[hit], body_velocity[tri[hit]])
        rel = v[hit] - vb
        vn = np.sum(rel * nrm[hit], axis=1)
        inward = np.minimum(vn, 0.0)
        tang = rel - vn[:, None] * nrm[hit]
        speed = np.linalg.norm(tang, axis=1)
        keep = np.where(speed > 0, np.maximum(0.0, 1.0 - s.friction * (-inward) / np.maximum(speed, 1e-12)), 1.0)
        v[hit] = vb + tang * keep[:, None] + np.maximum(vn, 0.0)[:, None] * nrm[hit]
        return x, v, int(hit.sum())

    def simulate(self, initial, boundary_targets, bodies=None, body_faces=None, fps=25.0):
        """Positions [T, N, 3] from ``initial`` at rest; ``boundary_targets`` [T, K, 3] (rows in the
        sorted boundary order), ``bodies`` [T, Nb, 3] or None. Returns (positions, steps per frame)."""
        T = len(boundary_targets)
        frame_dt = 1.0 / fps
        sub = max(1, math.ceil(frame_dt / self.max_step))
        h = frame_dt / sub
        x = np.array(initial, dtype=np.float64)
        v = np.zeros_like(x)
        out = np.empty((T, len(x), 3))
        out[0] = x
        minv = np.where(self.free, 1.0 / self.mass, 0.0)[:, None]
        body_faces = None if body_faces is None else np.asarray(body_faces, dtype=np.int64)
        for f in range(1, T):
            if bodies is not None:
                body_vel = (bodies[f] - bodies[f - 1]) / frame_dt
            for k in range(sub):
                w1 = (k + 1) / sub
                v = v + h * minv * self.forces(x, v)
                x = x + h * v
                target = (1 - w1) * boundary_targets[f - 1] + w1 * boundary_targets[f]
                x[self.boundary] = target
                v[self.boundary] = (boundary_targets[f] - boundary_targets[f - 1]) / frame_dt
                if bodies is not None:
                    body = (1 - w1) * bodies[f - 1] + w1 * bodies[f]
                    tree = cKDTree(body[body_faces].mean(axis=1))
                    x, v, _ = self.collide(x, v, body, body_vel, body_faces, tree)
                if not np.all(np.isfinite(x)):
                    raise FloatingPointError(f"foreign simulator blew up at frame {f}")
            out[f] = x
        return out, sub
