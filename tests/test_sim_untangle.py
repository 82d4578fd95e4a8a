"""Cloth left inside or through the body after a pinch is moved out at the next step (sim.untangle)."""

import cloth_grid
import ipctk
import numpy as np
import trimesh

from physavatar.sim import ClothSim, Material, SimSettings
from physavatar.sim.crease import winding_numbers
from physavatar.sim.untangle import untangle


def box(extents=(0.3, 0.3, 0.2), subdivisions=3):
    """A closed, outward-oriented box centred at the origin (top face z = 0.1), ~2-4 cm faces."""
    m = trimesh.creation.box(extents=extents)
    V, F = m.vertices, m.faces
    for _ in range(subdivisions):
        V, F = trimesh.remesh.subdivide(V, F)
    return np.asarray(V, np.float64), np.asarray(F, np.int64)


def crossing_cloth_on_box():
    """A 10-cm cloth 2 mm above the box's top face, its middle vertices pushed 1 cm into the box:
    its edges there pass through the top face (as a pinch leaves it, docs/simulation.md "Session 24")."""
    V, F = cloth_grid.grid(8, 0.1, 0.0, center=True)
    V = V + [0.0, 0.0, 0.102]
    x = V.copy()
    deep = np.linalg.norm(V[:, :2], axis=1) < 0.03
    x[deep, 2] = 0.09
    return V, F, x, deep


def test_cloth_through_a_moving_body_after_a_pinch_is_out_after_one_step():
    """The cloth crosses the box's top face (12 vertices 1 cm inside) at the start of a step that
    follows a pinch (the solver state's ``crease_check``, which a lagging step sets), and the box
    slides 1 cm a step. After one step no cloth vertex is inside the box (winding number) and
    nothing crosses it (ipctk), and so for three more steps. Before session 24 the crease rule's
    release-and-pull acted alone: the released cloth is out of the box's contact, the sliding box
    carries nothing, and cloth stayed inside and through the box."""
    V, F, x, deep = crossing_cloth_on_box()
    B0, Fb = box()
    assert deep.sum() == 12 and np.sum(winding_numbers(x, B0, Fb) > 0.5) == 12 and cloth_grid.body_crossings(x, F, B0, Fb)
    sim = ClothSim(V, F, Material(), SimSettings(friction=0.0), [])
    sim.set_state(sim.get_state() | {"crease_check": True})  # as after a step whose body lagged
    v, B = np.zeros_like(x), B0
    for k in range(4):
        B1 = B0 + [0.01 * (k + 1), 0.0, 0.0]
        x, v, st = sim.step(x, v, B, B1, Fb)
        B = B1
        assert st.body_gap == 0.0
        assert np.sum(winding_numbers(x, B, Fb) > 0.5) == 0, k
        assert not cloth_grid.body_crossings(x, F, B, Fb), k
        if k == 0:
            assert st.untangled_vertices >= 12  # the 12 inside, and the ring whose edges cross
    assert np.all(np.isfinite(x))


def test_untangle_leaves_cloth_outside_the_body_as_it_is():
    """Nothing inside or through the body: the same array back, nothing moved (a step after a
    pinch with clean cloth is simulated as without this rule)."""
    V, F, x, _ = crossing_cloth_on_box()
    B, Fb = box()
    sim = ClothSim(V, F, Material(), SimSettings(), [])
    sim.prepare(B, Fb)
    out, moved = untangle(sim.scene, V, F, B, Fb, np.ones(len(V), bool), 1e-3)
    assert out is V and len(moved) == 0
    out, moved = untangle(sim.scene, x, F, B, Fb, np.ones(len(V), bool), 1e-3)
    assert len(moved) >= 12 and np.all(winding_numbers(out, B, Fb) < 0.5) and not cloth_grid.body_crossings(out, F, B, Fb)
    # moved only where it was inside or next to it, to 2 d̂ above the top face
    far = np.linalg.norm(V[:, :2], axis=1) > 0.05
    np.testing.assert_array_equal(out[far], x[far])
    np.testing.assert_allclose(out[moved, 2], 0.1 + 2e-3, atol=1e-9)


def test_simulate_moves_cloth_that_crosses_the_body_out_before_the_frame_is_written():
    """sim.simulate checks every frame's cloth against the body the sim holds (ipctk) and, where
    it crosses, moves it out before the frame is written. The cloth starts through the box's
    top face (as the CMU hop's frame 172 ended: an edge through the body, no lag, nothing that
    would make the solver look) and the box slides 1 cm a frame: no written frame after the
    start crosses it or has cloth inside. Before session 24 nothing looked (every frame crossed:
    the hop's frames 172–229); in session 24 the cloth was moved out at the next frame's first
    step, so the frame that ended crossing was written crossing (frame 1 here, the hop's 172)."""
    from physavatar.sim import simulate

    V, F, x, _ = crossing_cloth_on_box()
    B0, Fb = box()
    bodies = np.stack([B0 + [0.01 * k, 0.0, 0.0] for k in range(5)])
    reports = []
    X = simulate(V, F, Material(), bodies, Fb, fps=25.0, settings=SimSettings(friction=0.0), x0=x,
                 on_frame=lambda c, r: reports.append(r))
    crosses = [cloth_grid.body_crossings(X[f], F, bodies[f], Fb) for f in range(5)]
    inside = [int(np.sum(winding_numbers(X[f], bodies[f], Fb) > 0.5)) for f in range(5)]
    assert crosses == [True, False, False, False, False] and inside[1:] == [0, 0, 0, 0]
    assert reports[0]["untangled_vertices"] >= 12 and not any(r["lagged"] for r in reports)


def two_boxes():
    """A body that passes through itself, as Anny's collider at a crease: a box (top face
    z = 0.1) and a taller one overlapping its side (x ≥ 0.1). The first box's top-face vertices
    inside the second are buried, and their one-ring (x ≥ 0.0625) hidden from contact."""
    A, FA = box()
    B, FB = box((0.1, 0.3, 0.3))
    return np.vstack([A, B + [0.15, 0.0, 0.05]]), np.vstack([FA, FB + len(A)])


def body_only_crossings(x, F, B, Fb):
    """ipctk's exact test, cloth against body only (as simulate's written-frame check)."""
    X = np.vstack([x, B])
    faces = np.vstack([F, Fb + len(x)])
    mesh = ipctk.CollisionMesh(X, ipctk.edges(faces), faces)
    mesh.can_collide = ipctk.make_vertex_patches_filter(np.r_[np.zeros(len(x)), np.ones(len(B))].astype(np.int32))
    return ipctk.has_intersections(mesh, X)


def test_a_frame_crossing_the_body_next_to_its_crease_is_written_untangled():
    """Cloth 2 mm above the first box's top, next to where the second box rises out of it, with
    4 vertices pushed 5 mm into the box under the triangles that the crease rule hides (a
    corner buried in the other box), as the crease rule's steps leave cloth (the hop's full
    clip, written frame 164, docs/simulation.md "Session 25"). Those triangles are outside the
    other box there, so the crossing shows, and simulate's check counts it. The frame-end
    untangle lifts the cloth over the visible part of every triangle: frame 1 is written
    intersection-free, the cloth moved at most ~7 mm. Before (session 24's untangle, against
    the outer surface only) its result still crossed the hidden triangles and was not kept."""
    from physavatar.sim import simulate
    from physavatar.sim.crease import buried_vertices, grow

    B, Fb = two_boxes()
    hidden = grow(buried_vertices(B, Fb), Fb, 1)
    V, F = cloth_grid.grid(8, 0.08, 0.0, center=True)
    V = V + [0.05, 0.0, 0.102]
    x = V.copy()
    pit = np.linalg.norm(V[:, :2] - [0.07, 0.0], axis=1) < 0.015
    x[pit, 2] = 0.095
    from physavatar.geometry.intersect import intersecting_pairs

    crossed = {int(t) for _, t in intersecting_pairs(x, F, B, Fb)[0]}
    assert pit.sum() == 4 and crossed and all(hidden[Fb[t]].any() for t in crossed)
    bodies = np.stack([B] * 3)
    reports = []
    X = simulate(V, F, Material(), bodies, Fb, fps=25.0, settings=SimSettings(friction=0.0, self_contact=True),
                 x0=x, on_frame=lambda c, r: reports.append(r))
    assert [body_only_crossings(X[f], F, B, Fb) for f in range(3)] == [True, False, False]
    assert reports[0]["untangled_vertices"] >= 4
    assert np.all(winding_numbers(X[1], B, Fb) < 0.5)
    assert np.abs(X[1] - x).max() < 0.012  # lifted over the crossing, not carried to a far triangle


def test_a_crossing_on_the_visible_surface_counts_as_visible_whatever_the_rounding():
    """crossing_cloth(visible_in=) keeps a crossing when its point lies outside every other part
    of the body. On one convex box every crossing is on the visible surface, so the lifts must be
    those without the visibility test. The point lies on the crossed triangle, whose own
    contribution to the winding number there is +½ or −½ by rounding; taken at the point itself,
    about half the crossings read 1 and were dropped as hidden (session 26)."""
    from physavatar.sim.crease import crossing_cloth

    V, F, x, _ = crossing_cloth_on_box()
    B, Fb = box()
    plain = crossing_cloth(x, F, B, Fb, 1e-3)
    shown = crossing_cloth(x, F, B, Fb, 1e-3, visible_in=(B, Fb))
    lifted = np.isfinite(plain).all(axis=1)
    assert lifted.sum() >= 12
    np.testing.assert_array_equal(shown, plain)
