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
    # the chosen holds: the top band, all around (without the band limit: every vertex)
    assert b.any() and GV[b, 2].min() >= 1.40 - cfg.top_band - 1e-9, GV[b, 2].min()
    assert b.sum() == (GV[:, 2] >= 1.40 - cfg.top_band - 1e-9).sum()


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
    assert np.isclose(GV[b, 2].max(), 1.40) and GV[b, 2].min() >= 1.40 - cfg.top_band - 1e-9, GV[b, 2].min()
