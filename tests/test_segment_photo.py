"""The segmentation's photo-consistency evidence (segment._photo_term, from refine.photo_depths).

A visual hull bridges bare skin where no camera can carve it (between a dress's straps, under
the arms): there the hull floats a centimetre or two above the body, so the distance to the body
calls it garment, and on the demo the dress's colours are too close to the skin's to overrule it.
What the cameras do tell apart: a patterned garment is photo-consistent where the hull lies on
it (a patch correlates across the cameras), the empty space above plain skin is not. The rates
of that evidence on garment and body are learned from the vertices the other terms decide.
"""

from __future__ import annotations

import numpy as np
from cloth_grid import grid

from physavatar.camera import Camera, intrinsics, look_at

SKIN = np.array([0.80, 0.62, 0.52])


def _grid(n: int, half: float, z: float):
    return grid(n, 2 * half, z, center=True)  # n×n vertices on [-half, half]² at height z


def _cameras(size: int = 160):
    cams = []
    for k, (ax, ay) in enumerate([(0, 0), (0.5, 0), (-0.5, 0), (0, 0.5), (0, -0.5)]):
        eye = np.array([ax, ay, 1.0])
        cams.append(Camera(f"c{k}", size, size, intrinsics(size, size, 30.0), look_at(eye, (0, 0, 0), up=(0, 1, 0))))
    return cams


def test_photo_evidence_on_a_pattern_and_none_on_speckled_plain_skin():
    """refine.photo_depths on the plane z = 0: where it carries a pattern (x < 0) the cameras'
    patches correlate at the plane; where it is plain skin with each camera's own pixel noise
    (x > 0) they do not, although single pixels vary as much as on the pattern."""
    from physavatar.geometry.mesh import vertex_normals
    from physavatar.stages.prepare.config import RefineConfig
    from physavatar.stages.prepare.refine import photo_depths, view_cosines

    cams = _cameras()
    rng = np.random.default_rng(0)
    images = {}
    for c in cams:
        o, d = c.pixel_rays()
        p = o + (-o[2] / d[..., 2])[..., None] * d
        x, y = p[..., 0], p[..., 1]
        pattern = 0.5 + 0.3 * np.stack([np.sin(2 * np.pi * x / 0.05), np.sin(2 * np.pi * y / 0.05),
                                        np.sin(2 * np.pi * (x + y) / 0.07)], -1)
        img = np.where((x < 0)[..., None], pattern, SKIN) + rng.normal(0, 0.06, x.shape + (3,))
        images[c.name] = np.clip(img, 0, 1).astype(np.float32)
    V, F = _grid(15, 0.14, 0.0)
    N = vertex_normals(V, F)
    assert (N[:, 2] > 0.99).all()
    fp = float(np.linalg.norm(cams[0].center) / cams[0].K[0, 0])
    off, score, used = photo_depths(V, N, cams, images, RefineConfig(), view_cosines(V, N, cams, 0.01), fp)
    pattern, skin = V[:, 0] < -0.03, V[:, 0] > 0.03
    assert (used[pattern | skin] >= 2).all()
    # measured: every pattern vertex, at most 4 mm (1.2 pixel footprints) off the plane; no skin vertex
    assert (score[pattern] > 0).mean() > 0.9, (score[pattern] > 0).mean()
    assert np.abs(off[pattern & (score > 0)]).max() < 2 * fp
    assert (score[skin] > 0).mean() < 0.1, (score[skin] > 0).mean()


def test_a_hull_bridge_over_bare_skin_without_evidence_is_body():
    """A hull over the body plane: lying on it (y > 0.08, body), 3 cm above it on a patterned
    garment (x < 0.06), and 1.5 cm above it elsewhere: the bulge of a hull over bare skin. The
    images are one grey (colour and the cameras' agreement under a vertex say nothing), the
    photo evidence is what refine.photo_depths gives such a scene: on the garment, nowhere else.
    Without it (the behaviour before) the distance alone makes the bridge garment."""
    from physavatar.stages.prepare.config import SegmentConfig
    from physavatar.stages.prepare.segment import segment

    cams = _cameras(120)
    images = {c.name: np.full((c.height, c.width, 3), 0.5, np.float32) for c in cams}
    BV, BF = _grid(31, 0.3, 0.0)
    V, F = _grid(21, 0.2, 0.0)
    body = V[:, 1] > 0.08
    garment = ~body & (V[:, 0] < 0.06)
    bridge = ~body & ~garment
    V[:, 2] = np.where(body, -0.002, np.where(garment, 0.03, 0.015))
    photo = garment.astype(np.float64)
    cfg = SegmentConfig(smoothness=0.5)
    old, _ = segment(V, F, BV, BF, cams, images, cfg, 0.02)
    new, info = segment(V, F, BV, BF, cams, images, cfg, 0.02, photo=photo)
    assert bridge.sum() >= 40 and garment.sum() >= 100
    assert (old[bridge] > 0).mean() > 0.9  # the old behaviour: the bridge is garment
    # evidence counts within one ring (a strap's patches straddle its edges): the bridge's first
    # column stays with the garment, the rest is body
    inner = bridge & (V[:, 0] > 0.06 + 0.025)
    assert (new[inner] == 0).all() and (new[bridge] == 0).mean() > 0.8, (new[bridge] > 0).sum()
    assert (new[garment] > 0).mean() > 0.95 and (new[body] == 0).all()
    assert info["photo"]["garment_rate"] > 0.9 and info["photo"]["body_rate"] < 0.1, info["photo"]


def test_a_garment_piece_ends_half_way_to_the_body_vertices():
    """garment_pieces keeps the faces two of whose corners are garment (a strap one vertex wide
    stays joined), so its third, body, corners come with it: a row of cloth a whole edge out on
    the skin. They move to the midpoints of their edges to the garment (segment._cut_outline),
    where the label changes."""
    from physavatar.stages.prepare.segment import garment_pieces

    BV, BF = _grid(31, 0.3, 0.0)
    V, F = _grid(11, 0.1, 0.05)  # 2 cm edges, a column at x = 0
    labels = (V[:, 0] < -0.01).astype(np.int64)  # garment up to the column x = -0.02
    (_, Vo, Fo), = garment_pieces(V, F, labels, BV, BF, cut_outline=False)
    (_, Vc, Fc), = garment_pieces(V, F, labels, BV, BF)
    assert np.array_equal(Fo, Fc) and abs(Vo[:, 0].max()) < 1e-9  # before: out to the body column
    edge = np.isclose(Vo[:, 0], 0.0)
    assert edge.sum() >= 9
    # the body column half way back (its edges to the garment: one straight, one diagonal, both
    # ending on x = -0.02), the rest unmoved
    assert np.allclose(Vc[edge, 0], -0.01), Vc[edge, 0]
    assert np.allclose(Vc[~edge], Vo[~edge])


def test_evidence_trims_a_garment_but_does_not_cut_its_strap():
    """keep_topology: a garment of two blocks joined by a strap two vertices wide (a grid mesh).
    The evidence takes away the strap and a flap on one block's edge; the flap goes (trimming
    keeps the topology), the strap is thinned but stays, so the garment stays one piece."""
    from physavatar.stages.prepare.evidence import keep_topology
    from physavatar.stages.prepare.segment import _components

    n = 21
    V, F = _grid(n, 0.2, 0.0)
    i, j = np.divmod(np.arange(n * n), n)  # row (x) and column (y) of each vertex
    a = (i >= 2) & (i <= 7) & (j >= 2) & (j <= 18)
    b = (i >= 13) & (i <= 18) & (j >= 2) & (j <= 18)
    strap = (i > 7) & (i < 13) & (j >= 9) & (j <= 10)
    flap = a & (j >= 15)
    before = a | b | strap
    after = before & ~strap & ~flap
    assert _components(after, F, n * n)[0] == 2  # what the evidence alone would do
    out, kept = keep_topology(before, after, F, np.arange(n * n))
    assert _components(out, F, n * n)[0] == 1 and kept >= 5 and (out & strap).sum() == kept
    assert not (out & flap).any() and np.array_equal(out & ~strap, after)
