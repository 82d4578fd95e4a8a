"""Boundary choice (stages/prepare/boundary.py) on a tight bodice: a garment tube in contact with
a body tube from its top (shoulders, z = 1.40 m) down to the hips (0.80 m). The contact region is
one, from top to bottom; the hold is its top band, not the whole bodice (demo capture, masks
computed, fitted body: 274 vertices chosen from 0.83 to 1.39 m, 23 cm from the true straps)."""

from __future__ import annotations

import numpy as np
from cloth_grid import tube

from physavatar.camera import ring_rig


def _tube(radius: float, z0: float, z1: float):
    return tube(radius, z0, z1, 24, 31)


def test_a_bodice_in_contact_all_along_is_held_at_its_top():
    from physavatar.stages.prepare.boundary import find_boundary
    from physavatar.stages.prepare.config import BoundaryConfig

    BV, BF = _tube(0.12, 0.0, 1.6)
    GV, GF = _tube(0.13, 0.80, 1.40)
    cams = ring_rig(4, 3.0, 1.0, (0, 0, 0.9), 64, 64, 50.0)
    frames = np.stack([BV, BV + [0.0, 0.0, 0.01]])  # the body moves a little: the bodice follows it
    cfg = BoundaryConfig()
    b, info = find_boundary(GV, GF, frames, BF, cams, lambda i: {c.name: np.ones((64, 64)) for c in cams}, [0, 1],
                            cfg)
    assert info["contact"] == len(GV) and info["regions_kept"] == 1
    # the chosen holds: the top band and ``grow_along`` along the tube below it, all around (without the
    # band limit: every vertex)
    low = 1.40 - cfg.top_band - cfg.grow_along - 1e-9
    assert b.any() and GV[b, 2].min() >= low, GV[b, 2].min()
    assert b.sum() == (GV[:, 2] >= low).sum() < len(GV)


def test_a_top_the_body_does_not_carry_still_holds_the_band_under_it():
    """The top 8 cm (straps) in contact but outside the masks once carried (a fitted body a few
    pixels off in a side view): the hold grows over the contact up to the top, and is the band
    under it, not everything from the followed part's top up."""
    from physavatar.stages.prepare.boundary import find_boundary
    from physavatar.stages.prepare.config import BoundaryConfig

    BV, BF = _tube(0.12, 0.0, 1.6)
    GV, GF = _tube(0.13, 0.80, 1.40)
    cams = ring_rig(4, 3.0, 1.0, (0, 0, 0.9), 64, 64, 50.0)

    def masks(i):
        out = {}
        for c in cams:
            m = np.ones((64, 64))
            if i > 0:  # rows above z = 1.32 (at the axis) are background
                uv, _ = c.project(np.array([[0.0, 0.0, 1.32]]))
                m[: int(np.floor(uv[0, 1])) + 1] = 0
            out[c.name] = m
        return out

    cfg = BoundaryConfig()
    b, info = find_boundary(GV, GF, np.stack([BV, BV]), BF, cams, masks, [0, 1], cfg)
    assert info["candidates"] < info["contact"] == len(GV)
    assert np.isclose(GV[b, 2].max(), 1.40) and GV[b, 2].min() >= 1.40 - cfg.top_band - cfg.grow_along - 1e-9, GV[b, 2].min()


def _ridge(ds: float = 0.01, front_deg: float = 30.0, back_deg: float = 70.0):
    """A strap over a shoulder-like ridge along x (crest at y 0, z 1.40 m): the garment strip follows
    the profile (front down at ``front_deg`` to y < 0, back at ``back_deg``), 3 columns 2 cm apart,
    a vertex every ``ds`` of arc length s (< 0 in front); the body is the same profile 5 mm lower
    and wider. Returns (garment V, F, arc length s per vertex, body V, F)."""
    def profile(s):
        a = np.radians(np.where(s < 0, front_deg, back_deg))
        return np.c_[s * np.cos(a), 1.40 - np.abs(s) * np.sin(a)]

    def grid(s, x):
        S, X = np.meshgrid(s, x, indexing="ij")
        yz = profile(S.ravel())
        V = np.c_[X.ravel(), yz]
        n = len(x)
        f = [[i * n + j, (i + 1) * n + j, i * n + j + 1] for i in range(len(s) - 1) for j in range(n - 1)]
        f += [[(i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1] for i in range(len(s) - 1) for j in range(n - 1)]
        return V, np.array(f), S.ravel()

    s = np.round(np.arange(-0.15, 0.12 + 1e-9, ds), 6)
    GV, GF, gs = grid(s, np.array([-0.02, 0.0, 0.02]))
    BV, BF, _ = grid(np.linspace(-0.3, 0.3, 61), np.linspace(-0.2, 0.2, 9))
    return GV, GF, gs, BV - [0.0, 0.0, 0.005], BF


def test_a_strap_down_a_steep_back_is_held_further_along_the_garment_past_the_band():
    """The band is in height: 4 cm of height is 8 cm of strap down a 30° front but 4.3 cm down a 70°
    back. With ``grow_along`` 2 cm the holds then grow that far along the garment over the contact:
    analytic arc lengths s ∈ [-(0.04/sin 30° + 0.02), 0.04/sin 70° + 0.02] (demo, session 35: the
    prepared straps' back rows were missing, 0.161 → 0.149 held-out Chamfer); a vertex off the body
    is not grown onto. With 0 (the default, main's rule): s ∈ [-0.08, 0.0426]."""
    from physavatar.stages.prepare.boundary import find_boundary
    from physavatar.stages.prepare.config import BoundaryConfig

    GV, GF, s, BV, BF = _ridge()
    off = s < -0.095  # the strap's front end stands 5 cm off the chest: not in contact
    GV[off] -= [0.0, 0.05, 0.0]
    cams = ring_rig(4, 3.0, 1.0, (0, 0, 0.9), 64, 64, 50.0)
    front, back = 0.04 / np.sin(np.radians(30.0)), 0.04 / np.sin(np.radians(70.0))
    masks = lambda i: {c.name: np.ones((64, 64)) for c in cams}  # noqa: E731
    for along in (0.0, 0.02):  # 0: the default, the band alone
        cfg = BoundaryConfig(grow_along=along)
        assert cfg.top_band == 0.04
        b, info = find_boundary(GV, GF, np.stack([BV, BV]), BF, cams, masks, [0, 1], cfg)
        assert info["contact"] == (~off).sum()
        want = (s >= -min(front + along, 0.09) - 1e-9) & (s <= back + along + 1e-9)
        assert np.array_equal(b, want), (along, np.unique(s[b]), np.unique(s[want]))
    assert s[b].max() == 0.06 and s[b].min() == -0.09  # 2 rows further down the back than the band's 0.04
