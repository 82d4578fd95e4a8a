"""A strap cut across by the labels is joined again (stages/prepare/gaps.py, session 30)."""

import json

import numpy as np
import trimesh
from scipy.sparse.csgraph import connected_components

from physavatar.geometry.mesh import adjacency
from physavatar.stages.prepare.gaps import close_gaps
from physavatar.stages.prepare.segment import garment_pieces


def _wall(n: int = 31, h: float = 0.02):
    """A vertical grid (x across, z up) of 2-cm edges, x -0.3 .. 0.3, z 0 .. 0.6."""
    i, j = np.divmod(np.arange(n * n), n)
    V = np.stack([(j - n // 2) * h, np.zeros(n * n), i * h], 1)
    q = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    F = np.concatenate([np.stack([q, q + 1, q + n + 1], 1), np.stack([q, q + n + 1, q + n], 1)])
    return V, F


def _ring(V):
    """A panel (z <= 0.1) and a strap two vertices wide going up at x = -0.12 .. -0.1, over at
    z = 0.5 .. 0.52 and down at x = 0.1 .. 0.12 (a dress's strap over the shoulder, flattened)."""
    x, z = V[:, 0].round(3), V[:, 2].round(3)
    panel = z <= 0.1
    up = ((np.abs(x + 0.11) < 0.015) | (np.abs(x - 0.11) < 0.015)) & (z <= 0.52)
    over = (np.abs(z - 0.51) < 0.015) & (x >= -0.12) & (x <= 0.12)
    return panel | up | over


def _loops(F):
    m = trimesh.Trimesh(faces=F, process=False)
    e = m.edges_sorted
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    b = uniq[counts == 1]
    ids, inv = np.unique(b, return_inverse=True)
    A = adjacency(np.c_[inv.reshape(-1, 2), inv.reshape(-1, 2)[:, :1]], len(ids))
    return connected_components(A, directed=False)[0]


def test_a_strap_cut_over_the_top_is_one_garment_piece_again():
    """The strap's back (x = 0.1 .. 0.12) labelled body from z 0.38 to 0.48 (its top kept):
    without the join the garment is one piece with one open loop (the ring's window is open to the
    cut) and the cut's faces are missing; with it, the back's top (a local top, z = 0.36) joins the
    strap above across the 6-vertex cut, the only join: the window is a loop of its own again (2
    loops, as uncut) and faces run along x = 0.1 up the cut. The panel's flat top beside the window
    and the strap's top are left as they are."""
    V, F = _wall()
    whole = _ring(V)
    x, z = V[:, 0].round(3), V[:, 2].round(3)
    cut = whole & ~((x > 0.09) & (z > 0.37) & (z < 0.49))
    body = trimesh.creation.icosphere(2, radius=0.1)
    BV, BF = body.vertices - [0, 0, 2.0], np.asarray(body.faces)

    (_, V0, F0), = garment_pieces(V, F, whole.astype(np.int64), BV, BF, max_gap=0)
    assert _loops(F0) == 2  # the uncut ring: outline and window
    (_, Vc, Fc), = garment_pieces(V, F, cut.astype(np.int64), BV, BF, max_gap=0)
    assert _loops(Fc) == 1
    assert not ((np.abs(Vc[Fc].mean(1)[:, 0] - 0.11) < 0.02) & (np.abs(Vc[Fc].mean(1)[:, 2] - 0.43) < 0.03)).any()

    joins = []
    (_, Vj, Fj), = garment_pieces(V, F, cut.astype(np.int64), BV, BF, joins=joins)
    assert len(joins) == 1, joins
    assert np.isclose(joins[0]["climb"], 0.5 - 0.36, atol=0.021) and joins[0]["gap"] < 0.2
    json.dumps(joins, allow_nan=False)  # prepare.json takes it as it is: strict JSON, no inf
    assert _loops(Fj) == 2
    c = Vj[Fj].mean(1)
    for zc in np.arange(0.38, 0.49, 0.02):  # faces along the cut, within an edge of the strap's line
        assert ((np.abs(c[:, 0] - 0.11) < 0.03) & (np.abs(c[:, 2] - zc) < 0.015)).any(), zc
    assert np.abs(Vj[:, 0]).max() <= 0.3 + 1e-9


def test_a_hole_and_a_level_gap_are_not_joined():
    """close_gaps joins only a local top to garment above it, far through the garment: a panel
    with a hole (its rim's top is below more garment, but near through it) and two strips side by
    side at the same height (no climb) stay as they are."""
    V, F = _wall()
    x, z = V[:, 0].round(3), V[:, 2].round(3)
    panel = (z <= 0.3) & ~((np.abs(x) <= 0.06) & (z >= 0.1) & (z <= 0.2))
    strips = (np.isclose(x, -0.2) | np.isclose(x, -0.12)) & (z > 0.3) & (z <= 0.5)
    out, band, info = close_gaps(panel | strips, V, F)
    assert info == [] and not band.any() and np.array_equal(out, panel | strips)


def _bent_ring(V):
    """The flattened strap of ``_ring`` whose right side bends out between z = 0.3 and 0.5 (x =
    0.11 + 0.1 sin(pi (z - 0.3) / 0.2), two to three vertices wide): the strap's own line, not the
    straight way up."""
    x, z = V[:, 0], V[:, 2]
    panel = z <= 0.1 + 1e-9
    left = (np.abs(x + 0.11) < 0.015) & (z <= 0.52 + 1e-9)
    over = (np.abs(z - 0.51) < 0.015) & (x >= -0.12 - 1e-9) & (x <= 0.12 + 1e-9)
    xc = 0.11 + np.where((z > 0.3) & (z < 0.5), 0.1 * np.sin(np.pi * (z - 0.3) / 0.2), 0.0)
    right = (np.abs(x - xc) < 0.021) & (z <= 0.52 + 1e-9)
    return panel | left | over | right


def test_the_join_follows_the_garment_evidence_not_the_shortest_way():
    """The right side's bend (z 0.32 .. 0.48) labelled body, the images' evidence (log-odds) +3 on
    the whole strap, -3 on the skin. The join (the only one, from the lower part's top) runs, at
    length x (1 + 4 P(body)), along the bend: every way vertex on the strap; the shortest way
    (evidence_weight 0, session 30's) goes straight up over the skin, most of its vertices off it.
    Which top joins and its climb do not change."""
    V, F = _wall()
    whole = _bent_ring(V)
    x, z = V[:, 0], V[:, 2]
    cut = whole & ~((x > 0.09) & (z > 0.31) & (z < 0.49))
    evidence = np.where(whole, 3.0, -3.0)

    _, _, short = close_gaps(cut, V, F, evidence=evidence, evidence_weight=0)
    out, band, info = close_gaps(cut, V, F, evidence=evidence)
    assert len(short) == len(info) == 1, (short, info)
    assert np.isclose(info[0]["climb"], short[0]["climb"], atol=0.021)
    on_short = whole[short[0]["way"]].mean()
    on_new = whole[info[0]["way"]].mean()
    assert on_short < 0.5, on_short  # the straight way up crosses the skin
    assert on_new == 1.0, on_new  # the evidence's way stays on the strap
    assert info[0]["gap"] > info[0]["shortest"]  # longer than the shortest, as the bend is
    assert (V[info[0]["way"], 0] > 0.15).any()  # it reaches the bend's far side



def test_a_widened_band_covers_the_cut_strap_across():
    """The session-30 ring's strap is two vertices wide (x = 0.10, 0.12); cut from z 0.38 to 0.48,
    the one-vertex way (``widen`` 0) labels garment only about half of the cut strap's vertices;
    one ring wider (``widen`` 1, prepare's default) all of them, and no vertex farther than one
    edge from the way. The faces across the strap are kept by ``garment_pieces``: the piece has
    faces at both x = 0.10 .. 0.12 and the way's other side all along the cut."""
    V, F = _wall()
    whole = _ring(V)
    x, z = V[:, 0].round(3), V[:, 2].round(3)
    gone = whole & (x > 0.09) & (z > 0.37) & (z < 0.49)
    cut = whole & ~gone
    one, _, info = close_gaps(cut, V, F)
    wide, band, info_w = close_gaps(cut, V, F, widen=1)
    assert [j["way"] for j in info] == [j["way"] for j in info_w]
    assert one[gone].mean() < 0.7, one[gone].mean()
    assert wide[gone].all()
    way = V[info_w[0]["way"]]
    d = np.linalg.norm(V[wide & ~cut][:, None] - way[None], axis=2).min(1)
    assert d.max() <= 0.02 * np.sqrt(2) + 1e-9
    joins = []
    (_, Vj, Fj), = garment_pieces(V, F, cut.astype(np.int64), *_far_body(), joins=joins, widen=1)
    c = Vj[Fj].mean(1)
    for zc in np.arange(0.39, 0.48, 0.02):
        row = c[(np.abs(c[:, 2] - zc) < 0.011) & (c[:, 0] > 0.05)]
        assert row[:, 0].max() - row[:, 0].min() >= 0.03, zc  # faces across the strap, not one edge


def _far_body():
    b = trimesh.creation.icosphere(2, radius=0.1)
    return b.vertices - [0, 0, 2.0], np.asarray(b.faces)


def test_a_strap_one_vertex_wide_is_not_cut_at_its_bow_ties():
    """Two panels (z <= 0.1, z >= 0.3) joined by a strip one vertex wide (x = 0): the faces with two
    garment corners meet at each strip vertex in two fans (bow-ties, not allowed in a template).
    Removing their faces (``fill_bowties=0``, before session 31) cuts the strip: two pieces, no face
    between the panels' edges; adding each bow-tie vertex's missing faces first keeps one piece with faces
    all along the strip, within an edge of it."""
    V, F = _wall()
    x, z = V[:, 0].round(3), V[:, 2].round(3)
    m = (z <= 0.1) | (z >= 0.3) | ((x == 0) & (z > 0.1) & (z < 0.3))
    for fill, n_pieces in ((0, 2), (2, 1)):
        (_, Vg, Fg), = garment_pieces(V, F, m.astype(np.int64), *_far_body(), max_gap=0, min_share=0.0,
                                      fill_bowties=fill)
        parts = trimesh.Trimesh(Vg, Fg, process=False).split(only_watertight=False)
        assert len(parts) == n_pieces, (fill, len(parts))
        c = Vg[Fg].mean(1)
        mid = c[(c[:, 2] > 0.11) & (c[:, 2] < 0.29)]
        rows = [bool((np.abs(mid[:, 2] - zc) < 0.011).any()) for zc in np.arange(0.12, 0.29, 0.02)]
        if fill:
            assert np.abs(mid[:, 0]).max() < 0.02 and all(rows), rows
        else:
            assert not any(rows[1:-1]), rows  # only the panels' own edge faces at the ends
