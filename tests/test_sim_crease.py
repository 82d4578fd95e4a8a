"""The body's own creases (sim.crease): cloth collides with the body's outer surface only."""

import cloth_grid
import ipctk
import numpy as np
import trimesh

from physavatar.sim import ClothSim, Material, SimSettings, simulate
from physavatar.sim.crease import buried_vertices, winding_numbers


def box(center, extents=(0.3, 0.3, 0.2), subdivisions=3):
    """A closed, outward-oriented box (trimesh), subdivided so that its faces are ~2-4 cm."""
    m = trimesh.creation.box(extents=extents)
    V, F = m.vertices, m.faces
    for _ in range(subdivisions):
        V, F = trimesh.remesh.subdivide(V, F)
    return np.asarray(V) + center, np.asarray(F)


def two_parts(dz):
    """Part A (0.3 m square, top face at z = 0) and part B (0.3 × 0.2 m, bottom face at
    z = 0.01 + dz), B shifted 0.18 m in x: where they overlap (0.03 < x < 0.15) B's bottom passes
    into A once dz < -0.01. One mesh."""
    VA, FA = box([0.0, 0.0, -0.1])
    VB, FB = box([0.18, 0.0, 0.11 + dz], (0.3, 0.2, 0.2))
    return np.vstack([VA, VB]), np.vstack([FA, FB + len(VA)])


def test_winding_numbers_find_the_vertices_one_part_buries_in_the_other():
    B, F = two_parts(-0.03)  # B's bottom 2 cm into A
    w = winding_numbers(B, B, F, np.arange(len(B)))
    buried = buried_vertices(B, F)
    n = len(B) // 2
    inside_a = (B[n:, 2] < 0.0) & (B[n:, 0] < 0.15)  # B's vertices inside A
    inside_b = (B[:n, 2] > -0.02) & (B[:n, 0] > 0.03) & (np.abs(B[:n, 1]) < 0.1)  # A's inside B
    assert inside_a.sum() > 10 and inside_b.sum() > 10
    np.testing.assert_array_equal(buried, np.r_[inside_b, inside_a])
    # a vertex's own part: its solid angle, 1/8 at a box corner, 1/2 on a face; another part adds 1
    assert np.all((w[~buried] > 0.1) & (w[~buried] < 0.9)) and np.all((w[buried] > 1.1) & (w[buried] < 1.9))
    # points: inside one part 1, inside both 2, outside 0
    w = winding_numbers([[0.0, 0.0, -0.1], [0.1, 0.0, -0.005], [0.0, 0.0, 0.5]], B, F)
    np.testing.assert_allclose(w, [1.0, 2.0, 0.0], atol=1e-9)


def test_cloth_between_two_body_parts_that_close_is_not_pinched():
    """A cloth lies between two parts of one body mesh that pass into each other (B's bottom
    moves 2 cm down, 1 cm into A, over the cloth). With the outer-surface rule off
    (crease_ring -1) the cloth is pinched: no room, the step gives up and the body lags. With it,
    the triangles each part buries in the other are not collision surface: the body reaches its
    pose, with no intersection against the surface the cloth collides with. (The cloth falls
    into A there: A's top is inside B at the step's end.) When B lifts off again the cloth, left
    inside A, is released and pulled out: within four steps no vertex is inside the body and
    nothing crosses the whole body mesh."""
    V, F = cloth_grid.grid(6, 0.08, 0.005, center=True)
    V = V + [0.09, 0.0, 0.0]
    B0, Fb = two_parts(0.0)
    B1, _ = two_parts(-0.02)
    B2, _ = two_parts(0.02)
    gaps = {}
    for ring in (-1, SimSettings().crease_ring):
        sim = ClothSim(V, F, Material(), SimSettings(friction=0.0, crease_ring=ring), [])
        sim.crease_on = True  # (simulate turns it on for a retry; off by default)
        x, v, st = sim.step(V, np.zeros_like(V), B0, B1, Fb)
        gaps[ring] = st.body_gap
        body = B1 if sim._body_lag is None else sim._body_lag[1]
        assert not sim.scene.has_intersections(np.vstack([x, body]))  # the surface it collides with
        if ring < 0:
            continue
        assert st.buried_vertices > 0 and st.body_gap == 0.0
        x, v, st = sim.step(x, v, B1, B2, Fb)
        assert st.released_vertices > 0 and st.body_gap == 0.0
        for _ in range(3):
            x, v, st = sim.step(x, v, B2, B2, Fb)
        assert np.all(winding_numbers(x, B2, Fb) < 0.5)  # all of the cloth outside the body
        assert not cloth_grid.body_crossings(x, F, B2, Fb)
    assert gaps[-1] > 5e-3 and gaps[SimSettings().crease_ring] == 0.0


def test_simulate_retries_a_frame_that_lags_with_the_outer_surface_only():
    """sim.simulate uses the rule only for a frame that lagged without it: the pinch of the test
    above as a two-frame sequence lags with the rule off (crease_ring -1; one step a frame)
    and not with it (a second attempt of one step, with the rule)."""
    V, F = cloth_grid.grid(6, 0.08, 0.005, center=True)
    V = V + [0.09, 0.0, 0.0]
    B0, Fb = two_parts(0.0)
    B1, _ = two_parts(-0.02)
    reports = {}
    for ring in (-1, 1):
        rep = []
        simulate(V, F, Material(), np.stack([B0, B1]), Fb, fps=25.0, max_substeps=1,
                 settings=SimSettings(friction=0.0, crease_ring=ring, uncollapse=False),
                 on_frame=lambda c, r, rep=rep: rep.append(r))
        reports[ring] = rep[0]
    assert reports[-1]["lagged"] and reports[-1]["buried_vertices"] == 0
    assert not reports[1]["lagged"] and reports[1]["attempts"] == 2 and reports[1]["substeps"] == 1
    assert reports[1]["buried_vertices"] > 0


def test_kept_and_parallel_winding_numbers_are_the_same_bits(monkeypatch):
    """The body's winding numbers kept per pose (asked again, for more vertices, for another
    pose) and the parallel loop (used above crease.PARALLEL_WORK) equal the serial loop's bits."""
    from physavatar.sim import crease

    B, F = two_parts(-0.03)
    ref = winding_numbers(B, B, F, np.arange(len(B)))
    kept = crease._BodyWinding(size=2)
    rng = np.random.default_rng(0)
    part = np.flatnonzero(rng.random(len(B)) < 0.3)
    np.testing.assert_array_equal(kept.at(B, F, part), ref[part])
    B2 = B + np.array([0.0, 0.0, 0.05])  # another pose: its own numbers
    ref2 = winding_numbers(B2, B2, F, np.arange(len(B2)))
    np.testing.assert_array_equal(kept.at(B2, F, np.arange(len(B))), ref2)
    np.testing.assert_array_equal(kept.at(B, F, np.arange(len(B))), ref)  # the rest filled in
    assert len(kept.entries) == 2
    monkeypatch.setattr(crease, "PARALLEL_WORK", 0)
    np.testing.assert_array_equal(winding_numbers(B, B, F, np.arange(len(B))), ref)
    np.testing.assert_array_equal(buried_vertices(B2, F), ref2 > crease.BURIED)


def test_released_cloth_does_not_pinch_a_body_that_slides_past_it(monkeypatch):
    """Cloth pressed into part A (as above, by a cloth wider than the overlap) crosses A's top
    face: the released vertices inside, their neighbours outside. When A then slides sideways
    (1 cm a step), A's edges sweep along those crossing cloth edges. Releasing only the vertices
    inside (crease.RELEASE_RING 0, session 20) leaves the edges' outside ends in contact with A,
    the sweep is cut by CCD and the body lags; releasing their one-ring too (the default) lets A
    slide past: no lag, and no step runs out its penalty phase."""
    from physavatar.sim import crease

    V, F = cloth_grid.grid(12, 0.2, 0.005, center=True)
    V = V + [0.09, 0.0, 0.0]
    B0, Fb = two_parts(0.0)
    B1, _ = two_parts(-0.02)
    n = len(B0) // 2
    out = {}
    for ring in (0, crease.RELEASE_RING):
        monkeypatch.setattr(crease, "RELEASE_RING", ring)
        sim = ClothSim(V, F, Material(), SimSettings(friction=0.0), [])
        sim.crease_on = True
        x, v, st = sim.step(V, np.zeros_like(V), B0, B1, Fb)
        assert st.body_gap == 0.0 and np.sum(winding_numbers(x, B1, Fb) > 0.5) > 10  # pressed into A
        gaps, pen, Bp = [], [], B1
        for k in range(3):
            Bn = B1.copy()
            Bn[:n, 0] -= 0.01 * (k + 1)
            x, v, st = sim.step(x, v, Bp, Bn, Fb)
            assert st.released_vertices > 0
            gaps.append(st.body_gap)
            pen.append(st.penalty_iterations)
            Bp = Bn if sim._body_lag is None else sim._body_lag[1]
        out[ring] = gaps, pen
    assert crease.RELEASE_RING == 1
    assert max(out[0][0]) > 5e-4 and max(out[0][1]) >= SimSettings().max_penalty_iterations
    assert max(out[1][0]) == 0.0 and max(out[1][1]) < SimSettings().max_penalty_iterations


def test_a_lagging_steps_free_solve_ends_once_its_norm_stalls(monkeypatch):
    """The free solve after a confined lag (ClothSim.lag_stall_exit, on in simulate) ends once
    its stopping norm has made no new low for stall_window iterations; without it the same
    iterations run to max_newton_iterations (directions and line search stubbed: the norm falls
    to 0.5, then stays at 0.6)."""
    from physavatar.sim import solver as S
    from physavatar.sim.settings import StepStats

    V, F = cloth_grid.grid(5, 0.1)
    sim = ClothSim(V, F, Material(), SimSettings(), [])
    x, _, _ = sim.step(V, np.zeros_like(V), None, None, None)
    monkeypatch.setattr(S, "adapt_stiffness", lambda *a: None)
    monkeypatch.setattr(ClothSim, "_line_search", lambda self, sv, step, residual, stats: None)
    iterations = {}
    for stall in (False, True):
        norms = iter([1.0, 0.5] + [0.6] * 500)
        monkeypatch.setattr(ClothSim, "_newton_direction",
                            lambda self, sv, stats, norms=norms: (np.zeros_like(sv.X), 1.0, next(norms)))
        sv = S._Solve(X=x.copy(), penalty=False, X_goal=x.copy(), diag=1.0, lag_left=0, prev_min_dist=1.0,
                      lag_stall=stall)
        stats = StepStats()
        sim._newton(sv, stats)
        iterations[stall] = stats.newton_iterations
    assert iterations == {False: SimSettings().max_newton_iterations, True: 2 + ClothSim.stall_window}


def crease_with_a_ledge(dz):
    """A box A (side wall x = 0.1, top z = 0.1 + dz) and a flatter box B (top z = 0.04 + dz)
    passing 1 cm into A's wall, its vertex columns 4 cm apart (x = 0.09 inside A, 0.13, ...):
    B's top-face triangles between x = 0.09 and 0.13 have a corner buried in A and straddle A's
    wall; their part at x > 0.1 is the body's visible surface."""
    VA, FA = box([0.0, 0.0, dz], (0.2, 0.2, 0.2))
    VB, FB = box([0.25, 0.0, dz], (0.32, 0.16, 0.08))
    return np.vstack([VA, VB]), np.vstack([FA, FB + len(VA)])


def test_a_crease_step_keeps_cloth_on_the_visible_part_of_the_triangles_next_to_the_crease():
    """Cloth 3 mm above B's top, over the visible part of the triangles next to the crease
    (x = 0.111–0.159, the crease at x = 0.1), the body rising 8 mm in one crease step (as the
    hop's knee, docs/simulation.md "Session 26"). The crease rule of session 20 leaves every
    triangle whose corners are all hidden (buried, or one ring from one: here x = 0.09–0.13)
    out of contact, so the body passes through the cloth there: ipctk finds the cloth crossing the body
    and cloth vertices end up to 2 cm below B's top. With ``crease_visible`` those triangles
    collide wherever the closest point lies outside the other part: the cloth is lifted with B's
    top (every vertex above the plane z = 0.048, the independent expectation), nothing crosses
    (ipctk), no cloth vertex is inside the body (winding number), the body reaches its pose."""
    V, F = cloth_grid.grid(7, 0.048, 0.0, center=True)
    V = V + [0.135, 0.0, 0.043]
    B0, Fb = crease_with_a_ledge(0.0)
    B1, _ = crease_with_a_ledge(0.008)
    faces = np.vstack([F, Fb + len(V)])
    result = {}
    for visible in (False, True):
        sim = ClothSim(V, F, Material(), SimSettings(), [])
        sim.crease_on, sim.crease_visible = True, visible
        x, v, st = sim.step(V, np.zeros_like(V), B0, B1, Fb)
        assert st.buried_vertices > 0 and st.body_gap == 0.0
        X = np.vstack([x, B1])
        mesh = ipctk.CollisionMesh(X, ipctk.edges(faces), faces)
        mesh.can_collide = ipctk.make_vertex_patches_filter(np.r_[np.zeros(len(V)), np.ones(len(B1))].astype(np.int32))
        result[visible] = (ipctk.has_intersections(mesh, X), float(x[:, 2].min() - 0.048),
                           int(np.sum(winding_numbers(x, B1, Fb) > 0.5)))
    assert result[False][0] and result[False][1] < -0.01  # session 20's rule: through the ledge
    crosses, above, inside = result[True]
    assert not crosses and above >= 0.0 and inside == 0
