"""prepare's 'clear' step (stages/prepare/clear.py): a prepared garment that crosses the body's
collider leaves it intersection-free by ipctk's exact test and at least d̂ off; a body through
the cloth is refused in one line naming the capture and the step."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from physavatar.errors import PhysavatarError
from physavatar.garment.garment import body_clearance
from physavatar.geometry import count_intersections
from physavatar.geometry.mesh import mesh_edges
from physavatar.sim import SimSettings
from physavatar.stages.prepare.clear import clear_of_body


def _template(body: trimesh.Trimesh, garment_V: np.ndarray, garment_F: np.ndarray, boundary: np.ndarray):
    """A template (body + garment vertices, faces, labels, boundary flags) as prepare writes it."""
    nb = len(body.vertices)
    V = np.concatenate([body.vertices, garment_V])
    F = np.concatenate([body.faces, garment_F + nb])
    labels = np.r_[np.zeros(nb, np.int64), np.ones(len(garment_V), np.int64)]
    return V, F, labels, np.r_[np.zeros(nb, bool), boundary]


def _cap_with_dents(seed: int = 0):
    """A 10-cm sphere (the body) and a cap of a finer sphere 4 mm off it (the garment, its rim the
    boundary), with 5 free vertices pushed 1 cm inside the body and 2 rim vertices 5 mm inside."""
    body = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    cloth = trimesh.creation.icosphere(subdivisions=4, radius=0.104)
    keep = cloth.vertices[:, 2] > 0.03
    ids = np.flatnonzero(keep)
    remap = -np.ones(len(cloth.vertices), np.int64)
    remap[ids] = np.arange(len(ids))
    GV, GF = np.array(cloth.vertices[ids]), remap[cloth.faces[keep[cloth.faces].all(1)]]
    edges = np.sort(np.concatenate([GF[:, [0, 1]], GF[:, [1, 2]], GF[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    rim = np.zeros(len(GV), bool)
    rim[uniq[count == 1].ravel()] = True
    rng = np.random.default_rng(seed)
    GV[rng.choice(np.flatnonzero(~rim), 5, replace=False)] *= 0.090 / 0.104
    GV[rng.choice(np.flatnonzero(rim), 2, replace=False)] *= 0.095 / 0.104
    return body, GV, GF, rim


def test_a_garment_through_the_body_is_pushed_clear():
    body, GV, GF, rim = _cap_with_dents()
    BV, BF = np.asarray(body.vertices), np.asarray(body.faces)
    assert count_intersections(GV, GF, BV, BF) > 0  # the case: the cloth crosses the body
    V, F, labels, boundary = _template(body, GV, GF, rim)
    out, info = clear_of_body(V, F, labels, boundary, BV, BF, source="capture")
    g = out[labels > 0]
    # ipctk's exact edge-triangle test, both ways: no crossing left; every pair at least d̂ apart
    assert count_intersections(g, GF, BV, BF) == 0
    dhat = SimSettings().dhat
    assert body_clearance(g, GF, BV, BF) >= dhat
    # the body is untouched; the push moved the dents (and their neighbours) only, the rim's too
    assert np.array_equal(out[labels == 0], V[labels == 0])
    step = np.linalg.norm(g - GV, axis=1)
    assert info["moved_vertices"] == int((step > 0).sum()) and 7 <= info["moved_vertices"] < 0.1 * len(GV)
    assert info["moved_boundary_vertices"] >= 2
    assert info["crossing_pairs_before"] > 0 and info["crossing_pairs_after"] == 0
    # vertices 1 cm inside move out by about that, not across the sphere
    assert 9e-3 < 1e-3 * info["max_move_mm"] < 2e-2
    # what references/physics do themselves (their boundary vertices stay) leaves crossings: the
    # step is needed, not a repeat of theirs
    assert info["left_with_boundary_fixed"] > 0


def test_a_clear_garment_is_left_as_it_is():
    body, GV, GF, rim = _cap_with_dents()
    cloth = trimesh.creation.icosphere(subdivisions=4, radius=0.104)
    GV = np.array(cloth.vertices[cloth.vertices[:, 2] > 0.03])  # no dents: 4 mm off everywhere
    V, F, labels, boundary = _template(body, GV, GF, rim)
    out, info = clear_of_body(V, F, labels, boundary, body.vertices, body.faces)
    assert np.array_equal(out, V) and info["moved_vertices"] == 0 and info["rounds"] == 0


def test_a_body_through_the_cloth_is_one_line_naming_the_step():
    # a thin rod (the body) through a coarse flat sheet: no vertex is inside, and pushing the
    # sheet's vertices out cannot free it
    rod = trimesh.creation.cylinder(radius=0.004, height=0.3, sections=3)
    xs = np.linspace(-0.1, 0.1, 3)
    X, Y = np.meshgrid(xs, xs)
    GV = np.c_[X.ravel() + 0.013, Y.ravel() + 0.007, np.zeros(9)]
    GF = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [3, 4, 7], [3, 7, 6], [4, 5, 8], [4, 8, 7]])
    assert len(mesh_edges(GF)) == 16 and count_intersections(GV, GF, rod.vertices, rod.faces) > 0
    V, F, labels, boundary = _template(rod, GV, GF, np.zeros(9, bool))
    with pytest.raises(PhysavatarError) as e:
        clear_of_body(V, F, labels, boundary, rod.vertices, rod.faces, source="/data/cap")
    msg = str(e.value)
    assert msg.startswith("/data/cap: prepare, step 'clear'") and "intersecting triangle pairs" in msg
    assert "\n" not in msg
