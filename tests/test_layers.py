"""Self-contact with sewn seams, and layered garments simulated together (issue 25 part 2)."""

import json

import numpy as np
import pytest
from cloth_grid import grid, tube

from physavatar.errors import PhysavatarError
from physavatar.garment_sim import GarmentPart, layered, push_over, split_layers
from physavatar.sim import Material, SimSettings
from physavatar.sim.contact import ContactScene
from physavatar.sim.simulate import seam_exclusions, self_contact_possible, self_intersecting_frames, simulate
from physavatar.sim.stitch import Stitch, seam_gaps

COTTON = Material(density=0.187, stretch_stiffness=30.9, bend_stiffness=2e-5, poisson=0.0)


def _book(n=8, size=0.2, angle_deg=20.0):
    """Two square panels sewn along x = 0 like the covers of a book opened by ``angle_deg``:
    panel A in the plane z = 0, panel B rotated up about the seam; the seam's vertices coincide
    (separate vertices of the mesh, paired as seams). Returns V, F, seam pairs, B's far edge."""
    V, F = grid(n, size)
    t = np.radians(angle_deg)
    VB = np.c_[V[:, 0] * np.cos(t), V[:, 1], V[:, 0] * np.sin(t)]
    seam = np.flatnonzero(V[:, 0] == 0)
    far = np.flatnonzero(np.isclose(V[:, 0], size)) + len(V)
    return np.vstack([V, VB]), np.vstack([F, F[:, ::-1] + len(V)]), np.c_[seam, seam + len(V)], far


def _box(x0, x1, y0, y1, z0, z1):
    P = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], float)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return P, F


def test_seam_exclusions_leave_out_exactly_the_primitives_that_touch_at_the_seam():
    V, F, seams, _ = _book()
    n = len(V) // 2
    ex = seam_exclusions(F, seams)
    # at rest the two covers touch along the seam: ipctk sees contacts at distance 0 (even an
    # "intersection") unless the seam's neighbourhood is left out
    assert not self_contact_possible(V, F, 1e-3)
    assert self_intersecting_frames(V[None], F) == [0]
    assert self_contact_possible(V, F, 1e-3, ex)
    assert self_intersecting_frames(V[None], F, ex) == []
    # every excluded pair joins the two panels, each vertex within one edge of the seam line
    edge = 0.2 / 7
    assert np.all(ex[:, 0] < n) and np.all(ex[:, 1] >= n)
    assert np.all(V[ex[:, 0], 0] <= edge + 1e-9) and np.all(np.hypot(V[ex[:, 1], 0], V[ex[:, 1], 2]) <= edge + 1e-9)
    # and every seam pair itself, with the rings: a ring of an inner seam vertex has 7 vertices
    assert set(map(tuple, seams)) <= set(map(tuple, ex))
    # three panels meeting at a vertex (a->b, a->c): b and c are joined through a, so (b, c)'s rings go too
    tri = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    ex3 = seam_exclusions(tri, np.array([[0, 3], [0, 6]]))
    assert {(3, 6), (4, 7), (0, 8)} <= set(map(tuple, ex3))


def test_a_sewn_garment_keeps_self_contact_and_its_layers_do_not_pass_through_each_other():
    """A box rises under the lower cover of the sewn book and pushes it into the upper one (held
    at its far edge). With self-contact (the seam left out) the covers stay apart and the seam
    closed on every frame; without it, the lower cover passes through the upper one."""
    V, F, seams, far = _book()
    ex = seam_exclusions(F, seams)
    P, PF = _box(0.06, 0.15, -0.05, 0.25, -0.04, -0.004)
    T = 9
    bodies = np.stack([P + [0, 0, z] for z in np.linspace(0, 0.06, T)])
    runs = {}
    for on in (True, False):
        runs[on] = simulate(V, F, COTTON, bodies, PF, boundary_indices=far, settings=SimSettings(self_contact=on),
                            extra_terms=[Stitch(seams)], contact_exclude=ex, max_substeps=4)
    X = runs[True]
    scene = ContactScene(V, F, P, PF, 1e-3)
    assert np.all(np.isfinite(X))
    assert not any(scene.has_intersections(np.vstack([X[f], bodies[f]])) for f in range(T))
    assert self_intersecting_frames(X, F, ex) == []
    assert seam_gaps(X[-1], seams).max() < 1e-4
    # the lower cover was lifted into where the upper one started (box top 5.6 cm at x = 0.1 m,
    # the upper cover 3.6 cm there): the layers were pushed together, not merely left apart
    mid_a = np.argmin(np.linalg.norm(V[: len(V) // 2] - [0.1, 0.1, 0], axis=1))
    assert X[-1, mid_a, 2] > 0.05
    assert len(self_intersecting_frames(runs[False], F, ex)) >= T // 2


def test_push_over_puts_a_garment_outside_the_one_under_it():
    """Two open cylinders about the z axis on a body cylinder of radius 0.08: the outer garment
    starts *inside* the inner one (r = 0.098 < 0.1); pushed over, every vertex of it ends at
    least the gap outside the inner cylinder's facets, and far from it barely anything moves."""
    def cylinder(r, n=24, m=6, z0=0.0, z1=0.3):
        return tube(r, z0, z1, n, m)

    body = cylinder(0.08, 24, 8, -0.2, 0.8)
    inner = cylinder(0.1)
    outer_V, outer_F = cylinder(0.098, 30, 12, 0.0, 0.6)  # reaches 0.3 m past the inner one's hem
    V = push_over(outer_V, outer_F, [inner], *body, gap=0.004)
    r = np.hypot(V[:, 0], V[:, 1])
    covered = outer_V[:, 2] <= 0.3
    inscribed = 0.1 * np.cos(np.pi / 24)  # the inner facets' distance from the axis at their middle
    assert r[covered].min() >= inscribed + 0.004 - 1e-9
    far = outer_V[:, 2] > 0.45  # 15 cm past the inner hem: barely touched by the smoothing
    assert np.linalg.norm(V[far] - outer_V[far], axis=1).max() < 1e-3
    part = layered([GarmentPart(np.arange(len(inner[0])), *inner, np.arange(24)),
                    GarmentPart(np.arange(len(V)), outer_V, outer_F, np.arange(30))], *body)
    assert self_contact_possible(part.vertices, part.faces, 1e-3)
    again = split_layers(part)
    assert [len(p.vertices) for p in again] == [len(inner[0]), len(V)]
    assert np.array_equal(again[0].faces, inner[1]) and np.array_equal(again[1].faces, outer_F)
    assert np.array_equal(again[1].boundary, np.arange(30))


def test_push_over_leaves_a_garment_below_the_hem_beside_it_not_lifted_onto_it():
    """Session 31 (layers-dance at 2 cm refused): the outer tube (r = 0.098, 1.5-cm rings) goes on
    0.3 m past the inner one's hem (r = 0.1, z = 0.3), still inside its radius. Its rings past the
    hem are beside the inner garment, not under it: they must not be lifted onto the hem (which
    crumpled the outer garment into itself, its layers then closer than d̂). Checked: the rings
    stay in their order along z, nothing moves more than the push the covered part needs
    (2 mm inside + 1.25 × the 4-mm gap: 7 mm, plus the facets' sagitta), and ipctk finds the
    layered start free of contacts within d̂ and of self-intersection."""
    body = tube(0.08, -0.2, 0.8, 24, 8)
    inner = tube(0.1, 0.0, 0.3, 24, 6)
    outer_V, outer_F = tube(0.098, 0.0, 0.6, 30, 40)
    V = push_over(outer_V, outer_F, [inner], *body, gap=0.004)
    z = V[:, 2].reshape(40, 30)
    assert np.all(z[1:].min(1) > z[:-1].max(1))  # no ring pulled past the next
    assert np.linalg.norm(V - outer_V, axis=1).max() < 0.002 + 1.25 * 0.004 + 0.1 * (1 - np.cos(np.pi / 24)) + 1e-3
    assert self_intersecting_frames(V[None], outer_F) == []
    part = layered([GarmentPart(np.arange(len(inner[0])), *inner, np.arange(24)),
                    GarmentPart(np.arange(len(V)), outer_V, outer_F, np.arange(30))], *body)
    assert np.array_equal(part.vertices[len(inner[0]):], V)
    assert self_contact_possible(part.vertices, part.faces, 1e-3)


def test_simulate_layers_a_tshirt_over_a_skirt_on_the_walk(tmp_path):
    from physavatar.stages import simulate as stage

    cfg = stage.SimulateConfig(edge_length=0.08, duration=0.2, preview=False, over="tshirt")
    r = stage.run(out=tmp_path / "out", config=cfg, garment="skirt", motion="walk")
    rec = json.loads((tmp_path / "out" / "config.json").read_text())
    assert rec["self_contact"] is True
    assert [x["garment"] for x in rec["layers"]] == ["skirt", "tshirt"]
    assert sum(x["vertices"] for x in rec["layers"]) == r.garment_vertices
    assert r.bad_frames == [] and r.self_intersecting_frames == [] and r.lagged_frames == []
    with pytest.raises(PhysavatarError, match="--over"):
        stage.run(out=tmp_path / "bad", config=stage.SimulateConfig(over="jacket"), garment="skirt", motion="walk")


def test_simulate_refuses_layers_that_start_closer_than_dhat_with_one_message(tmp_path, monkeypatch, caplog):
    """Layers stacked without the push over (a skirt on a skirt: coincident) are refused before the
    first step, the message naming the option, d̂ and the garments that start closest; no
    "simulated without self-contact" warning before it (nothing is simulated)."""
    from physavatar.stages import simulate as stage

    monkeypatch.setattr(stage, "layered", lambda parts, *body: layered(parts))  # stacked as they are
    cfg = stage.SimulateConfig(edge_length=0.08, duration=0.2, preview=False, over="skirt")
    with pytest.raises(PhysavatarError, match=r"--over.*closer than d̂ = 0.001 m.*0.000 mm apart: skirt and skirt"):
        stage.run(out=tmp_path / "out", config=cfg, garment="skirt", motion="walk")
    assert "without self-contact" not in caplog.text


def test_a_stitched_seam_is_not_a_rim_for_push_over():
    """Session 31's rim rule (push_over: a vertex whose closest point on the other garment is on
    its open edges is beside it, only its distance counts) must not take a garment file's seam
    (panels stitched, not welded: open edges in the mesh) for a hem. Two panels sewn along x = 0
    (_book): closest points on the seam's edges and vertices are rims without the seam pairs and
    are not with them; points on a panel's far edge are rims either way, points inside a
    triangle never; the seam's end on the panels' bottom edge is a rim (the hem's corner)."""
    from physavatar.garment_sim import _rim
    from physavatar.geometry import MeshQuery

    V, F, seams, far = _book(n=8, size=0.2, angle_deg=0.0)
    Q = MeshQuery(V, F)
    at_seam = np.array([[-0.01, 0.05, 0.0], [-0.01, 0.1, 0.0], [-0.02, 0.063, 0.0]])  # beyond the seam, in the plane
    at_far = np.array([[0.21, 0.05, 0.0], [0.21, 0.13, 0.0]])
    inside = np.array([[0.037, 0.061, 0.01]])
    _, f, w, q = Q.closest(np.vstack([at_seam, at_far, inside]))
    assert np.allclose(q[:3, 0], 0.0) and np.allclose(q[3:5, 0], 0.2)
    plain, sewn = _rim(F, len(V)), _rim(F, len(V), seams)
    assert plain(f, w).tolist() == [True, True, True, True, True, False]
    assert sewn(f, w).tolist() == [False, False, False, True, True, False]
    _, f0, w0, _ = Q.closest(np.array([[-0.02, -0.02, 0.0]]))  # the corner where seam and hem meet
    assert sewn(f0, w0).tolist() == [True]
