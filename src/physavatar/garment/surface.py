"""Where a garment lies around the body: front/back height fields over the frontal (x, z) plane.

Every garment here is sewn from a front and a back panel whose 2D pattern coordinates are the
world (x, z) of the front view (plus straps or sleeves that are part of those panels' outlines,
as in a kimono T-shirt pattern). A panel is lifted to 3D as a height field in y::

    front:  P(x, z) = (x, ymid(x, z) - D_front(x, z), z)
    back:   P(x, z) = (x, ymid(x, z) + D_back(x, z),  z)

where ``ymid`` is the body's smoothed mid-depth and ``D`` the garment's depth. ``D`` is at least the
body's depth plus the clearance wherever the body is (the garment never enters the body), and it
falls to zero at the seams (front and back meet there, so seams close exactly) with a bounded slope
``seam_slope``: the sewn "pillow" edge of real garments. Loose parts take the concave hull of the
depth across each row (a skirt spans the gap between the legs) and hang straight down from the hips.

All fields live on a regular grid (``cell`` metres) and are sampled bilinearly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

ARM_BONES = ("upperarm", "lowerarm", "wrist", "finger", "metacarpal")  # the shoulder cap stays with the torso
FOREARM_BONES = ("lowerarm", "wrist", "finger", "metacarpal")
HEAD_BONES = ("neck", "head", "eye")


@dataclass
class Grid:
    x0: float
    z0: float
    cell: float
    nx: int
    nz: int

    @property
    def xs(self):
        return self.x0 + self.cell * np.arange(self.nx)

    @property
    def zs(self):
        return self.z0 + self.cell * np.arange(self.nz)

    def index(self, x, z):
        return (np.asarray(x) - self.x0) / self.cell, (np.asarray(z) - self.z0) / self.cell

    def sample(self, field, x, z):
        """Bilinear sample of a [nx, nz] field at points (x, z) (clamped at the grid border)."""
        i, j = self.index(x, z)
        return ndimage.map_coordinates(field, [np.atleast_1d(i), np.atleast_1d(j)], order=1, mode="nearest")


def body_grid(body, cell=0.005, margin=0.08) -> Grid:
    v = body.rest_vertices
    x0 = float(v[:, 0].min()) - margin
    z0 = -margin
    nx = int(np.ceil((v[:, 0].max() + margin - x0) / cell)) + 1
    nz = int(np.ceil((v[:, 2].max() + margin - z0) / cell)) + 1
    return Grid(x0, z0, cell, nx, nz)


def raster_depth(body, grid: Grid, keep: np.ndarray, seed: int = 0, density: float = 6.0):
    """Front-most and back-most y of the kept body surface per (x, z) cell.

    The surface is sampled (``density`` samples per cell area on average) and each cell's extremes
    are dilated by one cell, so the raster errs on the side of a larger body (clearance is a
    lower bound). Returns ymin, ymax [nx, nz] with +inf / -inf where the body is absent.
    """
    V, F = body.rest_vertices, body.faces
    F = F[keep[F].all(axis=1)]
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n = int(density * area.sum() / grid.cell ** 2)
    rng = np.random.default_rng(seed)
    f = rng.choice(len(F), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    pts = tri[f, 0] * (1 - s)[:, None] + tri[f, 1] * (s * (1 - r2))[:, None] + tri[f, 2] * (s * r2)[:, None]
    pts = np.concatenate([pts, V[np.unique(F)]])
    i = np.clip(np.round((pts[:, 0] - grid.x0) / grid.cell).astype(int), 0, grid.nx - 1)
    j = np.clip(np.round((pts[:, 2] - grid.z0) / grid.cell).astype(int), 0, grid.nz - 1)
    ymin = np.full((grid.nx, grid.nz), np.inf)
    ymax = np.full((grid.nx, grid.nz), -np.inf)
    np.minimum.at(ymin, (i, j), pts[:, 1])
    np.maximum.at(ymax, (i, j), pts[:, 1])
    # fill sampling holes and dilate by one cell (conservative)
    ymin = ndimage.minimum_filter(ymin, size=3, mode="constant", cval=np.inf)
    ymax = ndimage.maximum_filter(ymax, size=3, mode="constant", cval=-np.inf)
    return ymin, ymax


def fill_smooth(values: np.ndarray, known: np.ndarray, sigma_cells: float) -> np.ndarray:
    """Normalized convolution: Gaussian-weighted average of the known values, defined everywhere."""
    w = ndimage.gaussian_filter(known.astype(float), sigma_cells, mode="nearest")
    s = ndimage.gaussian_filter(np.where(known, values, 0.0), sigma_cells, mode="nearest")
    out = s / np.maximum(w, 1e-12)
    # far from any known value the weights vanish: fall back to the nearest known value
    if (w < 1e-6).any():
        _, (ii, jj) = ndimage.distance_transform_edt(~known, return_indices=True)
        out = np.where(w < 1e-6, values[ii, jj], out)
    return out


def polygon_mask(grid: Grid, poly: np.ndarray) -> np.ndarray:
    """[nx, nz] bool: cell centres inside the closed polygon [n, 2] of (x, z)."""
    from matplotlib.path import Path

    X, Z = np.meshgrid(grid.xs, grid.zs, indexing="ij")
    return Path(poly).contains_points(np.c_[X.ravel(), Z.ravel()]).reshape(X.shape)


def polyline_distance(grid: Grid, polylines: list[np.ndarray], step: float = 0.0005) -> np.ndarray:
    """[nx, nz] distance (m) from each cell centre to the nearest of the polylines (sampled every
    ``step`` metres, so the distance is exact to step / 2)."""
    from scipy.spatial import cKDTree

    if not polylines:
        return np.full((grid.nx, grid.nz), np.inf)
    pts = []
    for pl in polylines:
        seg = np.linalg.norm(np.diff(pl, axis=0), axis=1)
        t = np.r_[0.0, np.cumsum(seg)]
        tt = np.linspace(0.0, t[-1], max(2, int(np.ceil(t[-1] / step)) + 1))
        pts.append(np.c_[np.interp(tt, t, pl[:, 0]), np.interp(tt, t, pl[:, 1])])
    X, Z = np.meshgrid(grid.xs, grid.zs, indexing="ij")
    d, _ = cKDTree(np.concatenate(pts)).query(np.c_[X.ravel(), Z.ravel()])
    return d.reshape(X.shape)


def seam_distance(grid: Grid, seams: list[np.ndarray], opens: list[np.ndarray], inside: np.ndarray) -> np.ndarray:
    """Distance to the seams, signed negative just outside them.

    The sign makes the field linear across a seam, so bilinear sampling puts D = 0 on the seam
    itself (an unsigned distance would give about a quarter cell of depth there). Outside the
    outline next to an open edge the distance stays positive, so sampling near open edges is not
    disturbed.
    """
    ds = polyline_distance(grid, seams)
    do = polyline_distance(grid, opens)
    return np.where(inside | (do < ds), ds, -ds)


def upper_concave_hull_rows(E: np.ndarray, inside: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per grid row j in ``rows``: the concave majorant of E[:, j] over the cells inside."""
    out = E.copy()
    for j in rows:
        idx = np.nonzero(inside[:, j])[0]
        if len(idx) < 3:
            continue
        x, y = idx.astype(float), E[idx, j]
        hull = []  # monotone chain, upper hull
        for p in zip(x, y):
            while len(hull) >= 2:
                (x1, y1), (x2, y2) = hull[-2], hull[-1]
                if (x2 - x1) * (p[1] - y1) - (y2 - y1) * (p[0] - x1) >= 0:
                    hull.pop()
                else:
                    break
            hull.append(p)
        hx, hy = np.array(hull).T
        out[idx, j] = np.interp(x, hx, hy)
    return out


def ball_offset(grid: Grid, d: np.ndarray, r: float) -> np.ndarray:
    """Height field offset by a ball of radius r: max over |x' - x| <= r of d(x') + sqrt(r² - |x' - x|²).

    Adding r to the depth only keeps r along the view direction; where the body's surface is
    steep (the sides of the arms and chest) the true normal distance would be much less. The
    ball offset keeps r in every direction.
    """
    out = np.full_like(d, -np.inf)
    k = int(np.floor(r / grid.cell))
    for i in range(-k, k + 1):
        for j in range(-k, k + 1):
            rho2 = (i * i + j * j) * grid.cell ** 2
            if rho2 > r * r:
                continue
            sh = np.full_like(d, -np.inf)
            xs = slice(max(i, 0), d.shape[0] + min(i, 0))
            xd = slice(max(-i, 0), d.shape[0] + min(-i, 0))
            zs = slice(max(j, 0), d.shape[1] + min(j, 0))
            zd = slice(max(-j, 0), d.shape[1] + min(-j, 0))
            sh[xd, zd] = d[xs, zs]
            out = np.maximum(out, sh + np.sqrt(r * r - rho2))
    return out


@dataclass
class PanelSurface:
    """The 3D lift of the front (side=-1) or back (side=+1) panel: P(x, z) = (x, ymid + side*D, z).

    Its pattern coordinates are not (x, z), which stretch where the cloth turns away from the
    viewer, but the panel's flattening (``flatten.FlatPanel``).
    """

    grid: Grid
    ymid: np.ndarray
    depth: np.ndarray
    side: float

    def __call__(self, xz: np.ndarray) -> np.ndarray:
        """Frontal-plane points (x, z) [n, 2] -> 3D [n, 3]."""
        xz = np.atleast_2d(xz)
        g = self.grid
        y = g.sample(self.ymid, xz[:, 0], xz[:, 1]) + self.side * g.sample(self.depth, xz[:, 0], xz[:, 1])
        return np.c_[xz[:, 0], y, xz[:, 1]]


def seam_lift(grid: Grid, ymid: np.ndarray):
    """Frontal-plane points (x, z) [n, 2] of a seam -> 3D: front and back meet at the mid-depth."""
    def lift(xz):
        xz = np.atleast_2d(xz)
        return np.c_[xz[:, 0], grid.sample(ymid, xz[:, 0], xz[:, 1]), xz[:, 1]]
    return lift


def garment_depth(grid: Grid, d_body: np.ndarray, inside: np.ndarray, dist_seam: np.ndarray, *,
                  clearance: float, ease: np.ndarray | float, seam_slope: float,
                  loose_below: float | None = None, hang_from: float | None = None,
                  flare_depth: float = 0.0, smooth_sigma: float = 0.015) -> np.ndarray:
    """Garment depth D [nx, nz] on one side of the mid surface (see module doc).

    Args:
        d_body: body depth beyond ymid on this side (-inf where the body is absent).
        inside: cells inside the panel outline.
        dist_seam: distance of each cell to the panel's seams (m).
        ease: extra looseness added to the body depth (m), scalar or [nx, nz].
        loose_below: rows below this z take the concave hull across the row (spans the legs).
        hang_from: rows below this z are at least as deep as the row above (the cloth hangs).
        flare_depth: extra depth per metre below ``hang_from`` (a flared skirt is rounder).
    """
    has = np.isfinite(d_body) & (d_body > -1.0)
    E0 = np.where(has, ball_offset(grid, np.where(has, np.maximum(d_body, 0.0), -np.inf), clearance), 0.0)
    E = np.where(has, E0 + ease, 0.0)
    sig = smooth_sigma / grid.cell
    E = fill_smooth(E, has, 2 * sig)
    zs = grid.zs
    if loose_below is not None:
        E = upper_concave_hull_rows(E, inside, np.nonzero(zs < loose_below)[0])
    if hang_from is not None:
        rows = np.nonzero(zs < hang_from)[0][::-1]  # from the top row down
        for a, b in zip(rows[:-1], rows[1:]):
            E[:, b] = np.maximum(E[:, b], E[:, a])
        E += flare_depth * np.clip(hang_from - zs, 0, None)[None, :]
    for _ in range(3):  # smooth, but never less than body depth + clearance
        E = np.maximum(ndimage.gaussian_filter(E, sig, mode="nearest"), E0)
    # Fall to zero at the seams with slope seam_slope: D = E tanh(k d / E) <= min(k d, E).
    k = seam_slope
    return E * np.tanh(k * dist_seam / np.maximum(E, 1e-6))
