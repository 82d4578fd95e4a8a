"""The garments' sewing patterns, drafted from the body's measurements.

Each design returns front and back ``Panel``s whose outlines are in the frontal (x, z) plane
(module doc of ``surface``) plus the seam lift and the boundary (Dirichlet) selection. Body
measurements come from rasters of the rest body (full topology): the torso's half-width per height
(arms and head excluded), the top of the shoulders and arms per column, and joint positions.
Margins between a seam and the body's silhouette follow from the seam slope k: a round body part
of radius r needs a margin of at least r / (2 k²) + clearance / k to stay under the seam's cone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..body.model import bone_vertex_mask
from . import surface as S
from .pattern import Panel, Piece

SEAM_SLOPE = 2.5


def bezier(p0, p1, p2, p3, n=24):
    t = np.linspace(0.0, 1.0, n)[:, None]
    p0, p1, p2, p3 = map(np.asarray, (p0, p1, p2, p3))
    return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t ** 2 * p2 + t ** 3 * p3


@dataclass
class BodyMeasure:
    """Rasters and landmarks of a rest body used to draft patterns."""

    body: object
    grid: S.Grid
    ymin: dict  # raster name -> [nx, nz]
    ymax: dict

    @staticmethod
    def of(body, seed: int = 0) -> "BodyMeasure":
        g = S.body_grid(body)
        arm = bone_vertex_mask(body, S.ARM_BONES)
        head = bone_vertex_mask(body, S.HEAD_BONES)
        fore = bone_vertex_mask(body, S.FOREARM_BONES)
        keeps = {"torso": ~arm & ~head, "upper": ~head & ~fore, "arms": arm & ~fore, "all": np.ones(len(arm), bool)}
        ymin, ymax = {}, {}
        for k, keep in keeps.items():
            ymin[k], ymax[k] = S.raster_depth(body, g, keep, seed=seed)
        return BodyMeasure(body, g, ymin, ymax)

    def joint(self, name):
        return self.body.rest_joints[self.body.bone_names.index(name)]

    def occupied(self, raster):
        return np.isfinite(self.ymin[raster])

    def half_width(self, raster="torso"):
        """Per grid row: max |x| of the raster (left/right symmetric), NaN in empty rows."""
        occ = self.occupied(raster)
        ax = np.abs(self.grid.xs)[:, None] * occ
        hw = ax.max(0)
        return np.where(occ.any(0), hw, np.nan)

    def hw_at(self, z, raster="torso"):
        hw = self.half_width(raster)
        zs = self.grid.zs
        ok = np.isfinite(hw)
        return np.interp(z, zs[ok], hw[ok])

    def top_at(self, x, raster="upper"):
        """Highest z of the raster in the column at |x| (max of both sides)."""
        occ = self.occupied(raster)
        zs = self.grid.zs
        top = np.where(occ.any(1), (zs[None, :] * occ + -1 * ~occ).max(1), np.nan)
        top = np.fmax(top, top[::-1]) if np.allclose(self.grid.xs, -self.grid.xs[::-1]) else top
        xs = self.grid.xs
        ok = np.isfinite(top)
        t = np.interp(np.abs(x), xs[ok], top[ok])
        t2 = np.interp(-np.abs(x), xs[ok], top[ok])
        return np.maximum(t, t2)

    def mid_and_depths(self, raster, sigma=0.02):
        """ymid [nx, nz] (smoothed mid-depth of the raster) and front/back depths beyond it."""
        lo, hi = self.ymin[raster], self.ymax[raster]
        has = np.isfinite(lo)
        mid = S.fill_smooth(np.where(has, 0.5 * (np.where(has, lo, 0.0) + np.where(has, hi, 0.0)), 0.0), has,
                           sigma / self.grid.cell)
        mid = ndimage.gaussian_filter(mid, 2 * sigma / self.grid.cell, mode="nearest")
        d_front = np.where(has, mid - np.where(has, lo, 0.0), -np.inf)
        d_back = np.where(has, np.where(has, hi, 0.0) - mid, -np.inf)
        return mid, d_front, d_back

    def armpit_z(self):
        """Lowest height where the upper arm comes within 2 cm of the torso's side."""
        occ = self.occupied("arms")
        hw = self.half_width("torso")
        zs, xs = self.grid.zs, np.abs(self.grid.xs)
        near = occ & (xs[:, None] <= np.nan_to_num(hw, nan=-1)[None, :] + 0.02)
        return float(zs[near.any(0)].min())


def _mirror_loop(right: list[Piece]) -> list[Piece]:
    """Full CCW outline from the right half (x >= 0) drawn from the bottom centre to the top centre.

    The first and last pieces cross the centre line and are joined with their mirror images; the
    others are mirrored to the left (x < 0) half with their seams renamed.
    """
    def mir(p):
        return np.c_[-p[:, 0], p[:, 1]]

    first, last, mid = right[0], right[-1], right[1:-1]
    pieces = [Piece(np.r_[mir(first.points)[::-1][:-1], first.points], first.seam, first.tag)]
    pieces += [Piece(p.points, None if p.seam is None else p.seam + ".L", p.tag) for p in mid]
    pieces.append(Piece(np.r_[last.points, mir(last.points)[::-1][1:]], last.seam, last.tag))
    pieces += [Piece(mir(p.points)[::-1], None if p.seam is None else p.seam + ".R", p.tag) for p in reversed(mid)]
    return pieces


def _side_curve(m: BodyMeasure, z_lo, z_hi, margin, hang_from=None, flare=0.0, n_step=0.01):
    """Side seam x(z) from z_lo up to z_hi: torso half-width + margin; below ``hang_from`` the seam
    hangs straight down from the widest point above and flares out by ``flare`` (dx/dz)."""
    z = np.linspace(z_lo, z_hi, max(3, int(np.ceil((z_hi - z_lo) / n_step)) + 1))
    x = m.hw_at(z) + margin
    if hang_from is not None:  # never narrower than below the widest point above
        x = np.maximum.accumulate(x[::-1])[::-1]
    x = ndimage.gaussian_filter1d(x, 2, mode="nearest")
    x = np.maximum(x, m.hw_at(z) + margin)
    if hang_from is not None:
        below = z < hang_from
        xh = np.interp(hang_from, z, x)
        x = np.where(below, np.maximum(x, xh + flare * (hang_from - z)), x)
        # a smooth run-in to the flare rather than a kink at the hips
        x = np.maximum(x, ndimage.gaussian_filter1d(x, 3, mode="nearest"))
    return np.c_[x, z]


@dataclass
class Design:
    panels: list
    seam_lift: object
    boundary: object  # callable(SewnMesh) -> [N] bool
    name: str


def _panels(m, outline_front, outline_back, raster, *, clearance, ease, loose_below=None, hang_from=None,
            flare_depth=0.0):
    mid, dfr, dbk = m.mid_and_depths(raster)
    panels = []
    for name, pieces, dbody, side in (("front", outline_front, dfr, -1.0), ("back", outline_back, dbk, 1.0)):
        poly = np.concatenate([p.points[:-1] for p in pieces])
        inside = S.polygon_mask(m.grid, poly)
        dist = S.seam_distance(m.grid, [p.points for p in pieces if p.seam is not None],
                               [p.points for p in pieces if p.seam is None], inside)
        D = S.garment_depth(m.grid, dbody, inside, dist, clearance=clearance, ease=ease, seam_slope=SEAM_SLOPE,
                            loose_below=loose_below, hang_from=hang_from, flare_depth=flare_depth)
        surf = S.PanelSurface(m.grid, mid, D, side)
        panels.append(Panel(name, pieces, surf, flip=side > 0, mirror_uv=side > 0))
    return panels, S.seam_lift(m.grid, mid)


def _near(sm, pattern_pts, radius):
    """[N] bool: vertices within ``radius`` in the frontal (x, z) plane of a polyline's points."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(pattern_pts).query(sm.vertices[:, [0, 2]])
    return d <= radius


def _dense(p, step=0.002):
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    t = np.r_[0, np.cumsum(seg)]
    tt = np.linspace(0, t[-1], max(2, int(t[-1] / step)))
    return np.c_[np.interp(tt, t, p[:, 0]), np.interp(tt, t, p[:, 1])]


def dress(m: BodyMeasure, h: float, clearance: float) -> Design:
    """Sleeveless long dress on two shoulder straps, fitted bodice, loose flared skirt to mid-calf."""
    knee, ankle = m.joint("lowerleg01.L")[2], m.joint("foot.L")[2]
    hip = m.joint("upperleg01.L")[2]
    shoulder = m.joint("upperarm01.L")
    z_hem = knee - 0.45 * (knee - ankle)
    z_ua = m.armpit_z() - 0.035  # underarm: below the armpit, clear of the upper arm
    z_waist = m.joint("spine03")[2]
    side = _side_curve(m, z_hem, z_ua, margin=0.02 + clearance, hang_from=z_waist, flare=0.22)
    x_si, x_so = 0.40 * shoulder[0], 0.70 * shoulder[0]  # strap between neck and shoulder joint
    z_b = z_ua + 0.045  # bodice top at the strap
    top = lambda x: m.top_at(x) + 0.015 + clearance  # noqa: E731
    xs_top = np.linspace(x_so, x_si, 6)
    hem_x = side[0, 0]
    right = [
        Piece(np.array([[0.0, z_hem], [hem_x, z_hem]]), tag="hem"),
        Piece(side, seam="side"),
        Piece(bezier((side[-1, 0], z_ua), (x_so + 0.5 * (side[-1, 0] - x_so), z_ua - 0.005),
                     (x_so, z_ua + 0.4 * (z_b - z_ua)), (x_so, z_b)), tag="armhole"),
        Piece(np.array([[x_so, z_b], [x_so, top(x_so)]]), tag="strap"),
        Piece(np.c_[xs_top, top(xs_top)], seam="strap", tag="strap_top"),
        Piece(np.array([[x_si, top(x_si)], [x_si, z_b]]), tag="strap"),
        Piece(bezier((x_si, z_b), (x_si, z_b - 0.03), (0.5 * x_si, z_b - 0.045), (0.0, z_b - 0.045)), tag="neck"),
    ]
    outline = _mirror_loop(right)
    ease = 0.012
    panels, seam_lift = _panels(m, outline, outline, "torso", clearance=clearance, ease=ease,
                                loose_below=hip - 0.03, hang_from=z_waist - 0.02, flare_depth=0.12)
    strap_top = np.concatenate([_dense(p.points) for p in outline if p.tag == "strap_top"])

    def boundary(sm):  # the straps on the shoulder tops: within 4 cm of the shoulder seam
        return _near(sm, strap_top, 0.04)

    return Design(panels, seam_lift, boundary, "dress")


def skirt(m: BodyMeasure, h: float, clearance: float) -> Design:
    """Flared skirt from the waist (waistband) to above the knee."""
    knee = m.joint("lowerleg01.L")[2]
    hip = m.joint("upperleg01.L")[2]
    z_waist = m.joint("spine03")[2]
    z_hem = knee + 0.10
    side = _side_curve(m, z_hem, z_waist, margin=0.015 + clearance, hang_from=hip - 0.02, flare=0.30)
    right = [
        Piece(np.array([[0.0, z_hem], [side[0, 0], z_hem]]), tag="hem"),
        Piece(side, seam="side"),
        Piece(np.array([[side[-1, 0], z_waist], [0.0, z_waist]]), tag="waist"),
    ]
    outline = _mirror_loop(right)
    panels, seam_lift = _panels(m, outline, outline, "torso", clearance=clearance, ease=0.004,
                                loose_below=hip, hang_from=hip - 0.02, flare_depth=0.15)

    def boundary(sm):  # the waistband: the waist edge and a band of 2 cm below it
        return sm.tags["waist"] | ((sm.vertices[:, 2] >= z_waist - max(0.02, 0.6 * h)))

    return Design(panels, seam_lift, boundary, "skirt")


def tshirt(m: BodyMeasure, h: float, clearance: float) -> Design:
    """T-shirt with short sleeves (kimono cut: sleeves drafted with the body panels), crew neck,
    hem at the hips."""
    hip = m.joint("upperleg01.L")[2]
    S_ = m.joint("upperarm01.L")[[0, 2]]
    E_ = m.joint("lowerarm01.L")[[0, 2]]
    u = (E_ - S_) / np.linalg.norm(E_ - S_)
    n_up = np.array([-u[1], u[0]])  # perpendicular, pointing up and out
    if n_up[1] < 0:
        n_up = -n_up
    margin = 0.02 + clearance
    upper_arm = np.linalg.norm(E_ - S_)
    # arm extent below its axis along the upper arm (from the arm raster), + margin
    occ = m.occupied("arms")
    X, Z = np.meshgrid(m.grid.xs, m.grid.zs, indexing="ij")
    rel = np.stack([X - S_[0], Z - S_[1]], -1)
    s_ax, s_perp = rel @ u, rel @ n_up
    band = occ & (s_ax > 0.0) & (s_ax < 0.8 * upper_arm) & (X > 0)
    r_under = float(-s_perp[band].min()) + margin
    z_hem = hip - 0.01
    z_neck = m.joint("neck01")[2]
    x_n = m.hw_at(z_neck + 0.03, "all") + margin * 0.5  # neck opening just wider than the neck
    top = lambda x: m.top_at(x) + 0.012 + clearance  # noqa: E731
    # armpit corner: where the under-sleeve line meets the side seam x = side(z)
    side_full = _side_curve(m, z_hem, S_[1], margin=margin + 0.01)
    ss = np.linspace(upper_arm, -0.3, 900)
    line = S_ + ss[:, None] * u - r_under * n_up
    x_side = np.interp(line[:, 1], side_full[:, 1], side_full[:, 0])
    k = np.argmax(line[:, 0] <= x_side)
    corner, s_corner = line[k], ss[k]
    # sleeve to the middle of the upper arm, with an underarm seam of at least 6 cm
    L_s = max(0.6 * upper_arm, s_corner + 0.06)
    # sleeve hem line: through S + L_s u, along n_up; its top corner where it meets the top seam
    H = S_ + L_s * u
    ts = np.linspace(0, 0.3, 301)
    hp = H + ts[:, None] * n_up
    t_top = ts[np.argmax(hp[:, 1] >= top(hp[:, 0]))]
    c_top = H + t_top * n_up
    c_bot = H - r_under * n_up
    # round the underarm (a fillet into the open armpit gap): a sharp reflex corner where the
    # side and underarm seams meet cannot be flattened without the pattern overlapping itself
    r_c = min(0.04, 0.45 * float(np.linalg.norm(c_bot - corner)))
    z_s = corner[1] - r_c
    side = side_full[side_full[:, 1] < z_s - 1e-3]
    p_side = np.array([np.interp(z_s, side_full[:, 1], side_full[:, 0]), z_s])
    side = np.r_[side, p_side[None]]
    p_under = corner + r_c * (c_bot - corner) / np.linalg.norm(c_bot - corner)
    t = np.linspace(0.0, 1.0, 16)[:, None]
    fillet = (1 - t) ** 2 * p_side + 2 * (1 - t) * t * corner + t ** 2 * p_under
    under = np.r_[fillet, c_bot[None]]
    xs_top = np.linspace(c_top[0], x_n, 40)
    top_seam = np.c_[xs_top, top(xs_top)]
    top_seam[0] = c_top
    top_seam[:, 1] = np.maximum(top_seam[:, 1], top(top_seam[:, 0]))

    def right(neck_drop):
        zc = top_seam[-1, 1]
        return [
            Piece(np.array([[0.0, z_hem], [side[0, 0], z_hem]]), tag="hem"),
            Piece(side, seam="side"),
            Piece(under, seam="under"),
            Piece(np.array([c_bot, c_top]), tag="sleeve"),
            Piece(top_seam, seam="top", tag="shoulder"),
            Piece(bezier((x_n, zc), (x_n, zc - 0.6 * neck_drop), (0.5 * x_n, zc - neck_drop), (0.0, zc - neck_drop)),
                  tag="neck"),
        ]

    front, back = _mirror_loop(right(0.075)), _mirror_loop(right(0.02))
    panels, seam_lift = _panels(m, front, back, "upper", clearance=clearance, ease=0.012)
    shoulder_line = _dense(top_seam[top_seam[:, 0] <= S_[0] + 0.01])
    shoulder_line = np.r_[shoulder_line, np.c_[-shoulder_line[:, 0], shoulder_line[:, 1]]]

    def boundary(sm):  # the shoulder seams (neck to shoulder joint) and 3 cm around them
        return _near(sm, shoulder_line, 0.03)

    return Design(panels, seam_lift, boundary, "tshirt")


DESIGNS = {"dress": dress, "skirt": skirt, "tshirt": tshirt}
