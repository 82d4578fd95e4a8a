"""Newton/IPC cloth stepping: statics, contact, invariance under mass scaling, determinism."""

import dataclasses

import ipctk
import cloth_grid
import numpy as np
import pytest
import trimesh

from physavatar.sim import ClothSim, Material, SimSettings, simulate


def grid(n, size, z=0.0):
    return cloth_grid.grid(n, size, z, center=True)


def settle_sag(material, n=7):
    """Sag of a 0.1 m square pinned at two opposite corners, after settling to rest."""
    V, F = grid(n, 0.1)
    pins = [0, n * n - 1]
    # Large implicit steps with mass damping reach the static equilibrium in a few steps.
    settings = SimSettings(dt=0.5, damping_mass=2.0, friction=0.0, newton_tol=1e-5)
    sim = ClothSim(V, F, material, settings, pins)
    x, v = V.copy(), np.zeros_like(V)
    for _ in range(30):
        x_old = x
        x, v, st = sim.step(x, v, None, None, None, V[pins])
        assert st.converged
        if np.abs(x - x_old).max() < 1e-7:
            break
    assert np.abs(x - x_old).max() < 1e-5  # at rest
    # The centre of mass lies on the diagonal through the pins, so gravity has no torque on
    # the rigid rotation about it; the free corners droop against bending and stretching.
    return -x[:, 2].min()


def test_sag_decreases_with_bending_and_membrane_stiffness():
    base = Material(density=0.15, stretch_stiffness=20.0, bend_stiffness=1e-6, poisson=0.3)
    by_kb = [settle_sag(dataclasses.replace(base, bend_stiffness=kb)) for kb in (1e-4, 1e-3, 1e-2)]
    by_ks = [settle_sag(dataclasses.replace(base, stretch_stiffness=ks)) for ks in (2.0, 20.0, 200.0)]
    assert by_kb[0] > by_kb[1] > by_kb[2] > 0
    assert by_ks[0] > by_ks[1] > by_ks[2] > 0
    assert by_kb[2] < 0.3 * by_kb[0]  # a stiff plate barely droops


def sphere():
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_cloth_dropped_on_sphere_never_intersects_and_comes_to_rest():
    V, F = grid(9, 0.3, z=0.12)
    B, BF = sphere()
    sim = ClothSim(V, F, Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5),
                   SimSettings(), [])
    x, v = V.copy(), np.zeros_like(V)
    speeds = []
    for _ in range(40):
        x, v, st = sim.step(x, v, B, B, BF)
        assert np.all(np.isfinite(x)) and np.all(np.isfinite(v))
        assert not ipctk.has_intersections(sim.scene.mesh, np.vstack([x, B]))
        assert st.converged
        speeds.append(np.abs(v).max())
    assert st.n_contacts > 0 and st.min_distance > 0
    assert x[:, 2].min() < 0.0  # draped over the sphere, not stuck on top
    assert speeds[-1] < 0.05 < max(speeds)  # fell, then came (nearly) to rest


def moving_body_case(material, steps=6, **kw):
    """A sphere rising into a cloth pinned at its corners (exercises the moving-body path)."""
    V, F = grid(7, 0.3, z=0.0)
    B0, BF = sphere()
    B0 = B0 + np.array([0, 0, -0.13])
    pins = [0, 6, 42, 48]
    settings = SimSettings(damping_mass=0.5, **kw)
    sim = ClothSim(V, F, material, settings, pins)
    x, v = V.copy(), np.zeros_like(V)
    traj = []
    for t in range(steps):
        b0 = B0 + np.array([0, 0, 0.012 * t])
        b1 = B0 + np.array([0, 0, 0.012 * (t + 1)])
        x, v, st = sim.step(x, v, b0, b1, BF, V[pins])
        assert st.converged
        assert not ipctk.has_intersections(sim.scene.mesh, np.vstack([x, b1]))
        traj.append(x)
    return np.array(traj), sim


def test_moving_body_pushes_cloth_without_intersection():
    traj, sim = moving_body_case(Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5))
    assert traj[-1][:, 2].max() > 0.01  # the rising sphere lifted the cloth


def test_scaling_density_and_stiffness_together_leaves_motion_unchanged():
    m = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5)
    a, _ = moving_body_case(m, newton_tol=1e-6)
    b, _ = moving_body_case(m.scaled(3.7), newton_tol=1e-6)
    # κ (ipctk's adaptive stiffness ∝ mass), friction (∝ κ) and mass damping all scale with ρ,
    # so E is multiplied by 3.7 and its minimiser is the same up to the Newton tolerance.
    assert np.abs(a - b).max() < 1e-5
    c, _ = moving_body_case(dataclasses.replace(m, density=0.15 * 3.7), newton_tol=1e-6)
    assert np.abs(a - c).max() > 1e-3  # changing ρ alone does change the motion


def test_same_inputs_give_bit_identical_results():
    V, F = grid(6, 0.3, z=0.11)
    B, BF = sphere()
    seq = np.stack([B + np.array([0.004 * t, 0, 0]) for t in range(6)])
    runs = [simulate(V, F, Material(), seq, BF, fps=25.0) for _ in range(2)]
    assert np.array_equal(runs[0], runs[1])
    assert runs[0].shape == (6, len(V), 3)


def test_step_expansion_changes_the_path_not_the_solution():
    """Doubling accepted full steps on a linearly converging tail (sim.linesearch.expand_step) ends
    at the same states as plain backtracking Newton, to the Newton tolerance."""
    m = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5)
    V, F = grid(7, 0.3, z=0.0)
    B0, BF = sphere()
    B0 = B0 + np.array([0, 0, -0.13])
    pins = [0, 6, 42, 48]
    runs, doublings = [], []
    for expand in (True, False):
        sim = ClothSim(V, F, m, SimSettings(damping_mass=0.5, newton_tol=1e-6, step_expansion=expand), pins)
        x, v, n = V.copy(), np.zeros_like(V), 0
        traj = []
        for t in range(6):
            b0, b1 = B0 + np.array([0, 0, 0.012 * t]), B0 + np.array([0, 0, 0.012 * (t + 1)])
            x, v, st = sim.step(x, v, b0, b1, BF, V[pins])
            assert st.converged
            n += st.step_expansions
            traj.append(x)
        runs.append(np.array(traj))
        doublings.append(n)
    assert doublings[0] > 0 and doublings[1] == 0  # the path did change
    assert np.abs(runs[0] - runs[1]).max() < 1e-5


def test_inexact_newton_directions_change_the_path_not_the_solution():
    """Loose CG on the directions that do not end a solve (SimSettings.newton_forcing) reaches
    the same states as solving every direction to 1e-6, to the Newton tolerance."""
    m = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5)
    # On the penalty path (follow_body off). From the carried start the cloth sits on a
    # faceted sphere with several nearby minima, and the two paths end 5.9 mm apart in
    # different ones (docs/simulation.md, "Moving collider").
    loose, _ = moving_body_case(m, newton_tol=1e-6, newton_forcing=1e-2, follow_body=0.0)
    tight, _ = moving_body_case(m, newton_tol=1e-6, newton_forcing=1e-6, follow_body=0.0)
    assert not np.array_equal(loose, tight)  # the path did change
    assert np.abs(loose - tight).max() < 1e-5


def test_acceleration_predictor_changes_the_newton_start_not_the_solution(monkeypatch):
    """Newton starts from x̃ + ĥ² aₜ (ClothSim.predict_acceleration): each step, from the same
    state, ends where the step from x̃ = xₜ + ĥ vₜ ends, to the Newton tolerance (a cloth
    swinging from two corners; with contact the step's potential can have several nearby
    minima, and any change of the start, warm_start on or off too, may pick another)."""
    n = 7
    V, F = grid(n, 0.1)
    pins = [0, n - 1]
    m = Material(density=0.15, stretch_stiffness=20.0, bend_stiffness=1e-5, poisson=0.3)
    sim = ClothSim(V, F, m, SimSettings(dt=0.02, newton_tol=1e-6, friction=0.0), pins)
    x, v = V.copy(), np.zeros_like(V)
    diffs, changed = [], False
    for _ in range(10):
        before = sim.get_state()
        monkeypatch.setattr(ClothSim, "predict_acceleration", True)
        x1, v1, st = sim.step(x, v, None, None, None, V[pins])
        assert st.converged
        after = sim.get_state()
        sim.set_state(before)
        monkeypatch.setattr(ClothSim, "predict_acceleration", False)
        x2, _, st = sim.step(x, v, None, None, None, V[pins])
        assert st.converged
        diffs.append(np.abs(x1 - x2).max())
        changed |= not np.array_equal(x1, x2)
        sim.set_state(after)
        x, v = x1, v1
    assert changed  # the start did change
    assert max(diffs) < 1e-6, diffs


def sheet_into_sphere(seed, z, dz):
    """A sheet at height z over the unit-test sphere, moved down by dz with noise: (V, B, scene,
    X0, X1, alpha) with alpha the move's collision-free step size."""
    from physavatar.sim.contact import ContactScene

    rng = np.random.default_rng(seed)
    V, F = grid(9, 0.3, z=z)
    B, BF = sphere()
    scene = ContactScene(V, F, B, BF, dhat=1e-3)
    X0 = np.vstack([V, B])
    X1 = X0.copy()
    X1[: len(V)] += rng.normal(scale=2e-3, size=V.shape) + np.array([0.0, 0.0, -dz])
    return V, B, scene, X0, X1, scene.collision_free_stepsize(X0, X1)


def test_segment_candidates_hold_the_barrier_set_of_every_point_on_the_segment():
    """The solver reuses the candidates of the line search's CCD segment for the barrier set
    at the accepted point (no rebuild): the set must equal one built around that point."""

    V, B, scene, X0, X1, alpha = sheet_into_sphere(3, 0.1005, 0.0015)
    assert 0 < alpha < 1  # the move runs into the sphere: the interesting case
    barrier = ipctk.BarrierPotential(1e-3, 1.0)

    def barrier_at(Xt):
        c = scene.collisions_at(Xt)
        return len(c), barrier(c, scene.mesh, Xt), barrier.gradient(c, scene.mesh, Xt)

    for t in (0.0, 0.3 * alpha, alpha):
        Xt = X0 + t * (X1 - X0)
        scene.prepare_segment(X0, X1)
        n_seg, e_seg, g_seg = barrier_at(Xt)
        scene.prepare_static(Xt)
        n_sta, e_sta, g_sta = barrier_at(Xt)
        assert n_sta > 0 and n_seg == n_sta  # (pairs may be listed in another order)
        assert e_seg == pytest.approx(e_sta, rel=1e-12)
        np.testing.assert_allclose(g_seg, g_sta, rtol=1e-10, atol=1e-12 * np.abs(g_sta).max())


def test_rms_stopping_rule_changes_where_newton_stops_not_the_solution():
    """Codim-IPC's stopping rule (SimSettings.newton_norm="rms": RMS over the free cloth
    vertices of ‖Δx_i‖ / h, step taken) ends at the states of the ∞-norm rule when both are
    tight, and its residual is that formula."""
    m = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5)
    # without the contact preview: with it, the two paths reach different nearby minima of the
    # first contact step on the faceted sphere (0.36 mm apart, energies 1e-4 apart relative;
    # docs/simulation.md "Session 21")
    rms, sim = moving_body_case(m, newton_tol=1e-6, newton_norm="rms", contact_preview=0.0)
    ref, _ = moving_body_case(m, newton_tol=1e-7, newton_norm="max", contact_preview=0.0)
    assert np.abs(rms - ref).max() < 1e-6
    step = np.random.default_rng(0).normal(size=(sim.n + sim.nb, 3))
    step[sim.boundary] = 0.0  # prescribed vertices do not move outside penalty mode
    h = sim.settings.dt
    free = np.setdiff1d(np.arange(sim.n), sim.boundary)
    expected = np.sqrt(np.mean(np.sum(step[free] ** 2, axis=1))) / h
    res_max, res_rms = sim._residuals(step, h)
    assert res_rms == pytest.approx(expected, rel=1e-12)
    assert res_max == pytest.approx(np.abs(step[: sim.n]).max() / h, rel=1e-12)


def test_threaded_ccd_gives_bit_identical_results():
    """The CCD narrow phase is a minimum over candidates: two threads give the same bits."""
    V, F = grid(6, 0.3, z=0.11)
    B, BF = sphere()
    seq = np.stack([B + np.array([0.004 * t, 0, 0]) for t in range(6)])
    runs = [simulate(V, F, Material(), seq, BF, fps=25.0, settings=SimSettings(ccd_threads=k)) for k in (1, 2, 2)]
    assert np.array_equal(runs[0], runs[1]) and np.array_equal(runs[1], runs[2])


def test_surface_carry_moves_points_rigidly_with_a_rigid_body():
    """A point carried by its closest body triangle (barycentric point + offset in the
    triangle's frame) moves exactly as the body does under a rigid motion, wherever it is."""
    from scipy.spatial.transform import Rotation

    from physavatar.sim.start import SurfaceCarry

    B, BF = sphere()
    P = np.random.default_rng(3).normal(size=(200, 3)) * 0.08  # inside, on and outside
    carry = SurfaceCarry(B, BF, P)
    R = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    t = np.array([0.05, -0.02, 0.1])
    assert np.abs(carry.at(B @ R.T + t) - (P @ R.T + t)).max() < 1e-12
    assert np.abs(carry.at(B) - P).max() < 1e-12
    assert np.all(carry.distance >= 0) and carry.distance.max() < 0.3


def test_follow_body_start_skips_the_penalty_phase_and_reaches_an_equally_low_minimum():
    """Starting a step with the cloth carried along by the body (SimSettings.follow_body)
    instead of the kinematic-penalty phase: no penalty iterations, every state intersection-
    free, and a minimiser of the same incremental potential. A rising sphere under a stiff
    cloth has several nearby local minima (the cloth settles on different facets), so the
    states are compared by their energy under one and the same step, not vertex by vertex."""
    m = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-2)
    V, F = grid(7, 0.3, z=0.0)
    B0, BF = sphere()
    B0 = B0 + np.array([0, 0, -0.13])
    pins = [0, 6, 42, 48]
    runs = {}
    for follow in (0.0, 0.05):
        sim = ClothSim(V, F, m, SimSettings(damping_mass=0.5, newton_tol=1e-6, friction=0.0, follow_body=follow), pins)
        x, v, penalty, follows = V.copy(), np.zeros_like(V), 0, 0
        for t in range(4):
            b0, b1 = B0 + np.array([0, 0, 0.012 * t]), B0 + np.array([0, 0, 0.012 * (t + 1)])
            x, v, st = sim.step(x, v, b0, b1, BF, V[pins])
            assert st.converged
            assert not ipctk.has_intersections(sim.scene.mesh, np.vstack([x, b1]))
            penalty += st.penalty_iterations
            follows += st.body_follows
        runs[follow] = (sim, x, b1, penalty, follows)
    sim, x_pen, b1, pen_its, _ = runs[0.0]
    _, x_fol, _, fol_its, follows = runs[0.05]
    assert pen_its > 0 and fol_its == 0 and follows >= 3
    assert x_pen[:, 2].max() > 0.01  # the sphere did push the cloth
    energy = []
    for xx in (x_pen, x_fol):  # both under the last step of the penalty run (same κ, x̃)
        X = np.vstack([xx, b1])
        sim.scene.prepare_static(X)
        energy.append(sim._energy(X, False))
    assert abs(energy[1] - energy[0]) < 5e-3 * abs(energy[0])
    assert np.abs(x_pen - x_fol).max() < 3e-3


def trampoline_trajectory(integrator, substeps, frames=6, fps=200.0, n=7):
    """A 30 cm square cloth held along its border, sagging from rest under gravity (smooth
    membrane-dominated dynamics), stepped by ClothSim itself (BDF2 takes its history from its
    own last step)."""
    V, F = grid(n, 0.3)
    border = np.flatnonzero(np.any(np.isclose(np.abs(V[:, :2]), 0.15), axis=1))
    settings = SimSettings(dt=1.0 / (fps * substeps), integrator=integrator, newton_tol=1e-6)
    sim = ClothSim(V, F, Material(density=0.1, stretch_stiffness=20.0, bend_stiffness=1e-6), settings, border)
    x, v = V.copy(), np.zeros_like(V)
    out = [x]
    for _ in range(frames - 1):
        for _ in range(substeps):
            x, v, st = sim.step(x, v, None, None, None)
            assert st.converged
        out.append(x)
    return np.array(out)


def test_bdf2_converges_at_second_order_and_implicit_euler_at_first():
    """Halving the step halves implicit Euler's error and quarters BDF2's (against BDF2 at
    1/32 of the step). A first-order start (or a lost history) would make BDF2 first order."""
    ref = trampoline_trajectory("bdf2", 32)
    assert ref[-1][:, 2].min() < -1e-3  # it sags by millimetres: the check is not vacuous
    for integrator, order in (("euler", 1), ("bdf2", 2)):
        err = [np.abs(trampoline_trajectory(integrator, k) - ref).max() for k in (1, 2, 4)]
        ratios = np.array(err[:-1]) / np.array(err[1:])
        np.testing.assert_allclose(ratios, 2.0**order, rtol=0.15)
    assert err[-1] < 0.2 * np.abs(trampoline_trajectory("euler", 4) - ref).max()


def test_unknown_integrator_is_refused():
    V, F = grid(3, 0.1)
    with pytest.raises(ValueError, match="integrator"):
        ClothSim(V, F, Material(), SimSettings(integrator="rk4"))


def test_body_that_leaves_no_room_lags_instead_of_crossing_the_cloth():
    """Two plates close through a cloth caught between them (they would pass through each
    other): no intersection-free state has the plates at their poses. The step gives up after
    max_penalty_iterations, keeps the intersection-free state it reached, and the next step goes
    on from where the plates got to (not from the poses it is given)."""
    V, F = grid(5, 0.1)
    P, PF = grid(3, 0.2)
    plates_t = np.vstack([P + [0, 0, 0.01], P + [0, 0, -0.01]])
    plates_t1 = np.vstack([P + [0, 0, -0.01], P + [0, 0, 0.01]])  # swapped: they cross
    Fb = np.vstack([PF, PF + len(P)])
    sim = ClothSim(V, F, Material(), SimSettings(max_penalty_iterations=8, friction=0.0), [])
    x, v, st = sim.step(V, np.zeros_like(V), plates_t, plates_t1, Fb)
    # (the free system converges once only the plates' pinched part is held back: sim.lag)
    assert st.penalty_iterations == 8 and st.body_gap > 1e-3 and st.lag_vertices > 0
    reached = sim._body_lag[1]
    scene = sim.scene
    assert not scene.has_intersections(np.vstack([x, reached]))
    assert scene.has_intersections(np.vstack([x, plates_t1])) or np.abs(reached - plates_t1).max() > 1e-3
    # the next step is given the poses the last one was meant to reach; it starts from the reached ones
    x2, v2, st2 = sim.step(x, v, plates_t1, plates_t1, Fb)
    assert st2.body_lagged and np.all(np.isfinite(x2))
    assert not scene.has_intersections(np.vstack([x2, sim._body_lag[1] if sim._body_lag else plates_t1]))


def test_prescribed_parts_that_pass_through_each_other_leave_the_step_free():
    """Issue 25 part 1 (the whole CMU clips lagged from frame 70): the dress's shoulder straps
    are attached to the body and ride its skin, which folds at the shoulder, so the prescribed
    strap triangles passed through each other. Contact between two prescribed primitives held
    the prescribed vertices back (penalty phase stalled: the step lagged, κ doubled). Here two
    cloth flaps are each attached along a strip; one strip's targets are moved, tilted, through the
    other's. No unknown can separate them: those pairs are left out (contact.prescribed_filter),
    the step converges with every attached vertex at its target and κ unchanged; the crossing
    of the prescribed strips themselves is in the input and the written-frame check sees it."""
    from physavatar.sim.simulate import self_intersecting_frames

    n = 5
    V, F = cloth_grid.grid(n, 0.1)
    X0 = np.vstack([V, V * [1, -1, 1] + [0, 0.0125, 0.004]])  # flap B 4 mm above A, mirrored
    FF = np.vstack([F, F[:, ::-1] + len(V)])
    strip = np.r_[np.arange(n) * n, np.arange(n) * n + 1]  # rows y = 0 and 0.025 (A); B's overlap them
    bnd = np.r_[strip, strip + len(V)]
    sim = ClothSim(X0, FF, Material(), SimSettings(friction=0.0, self_contact=True, max_penalty_iterations=20), bnd)
    x, v = X0.copy(), np.zeros_like(X0)
    ids = np.sort(bnd)
    kappa = None
    onB = ids >= len(V)
    edge = onB & ((ids - len(V)) % n == 0)  # B's row over A's strip (y = 0.0125)
    for z_edge, z_rest in ((0.002, 0.002), (-0.0005, 0.001)):  # then tilted through A's strip
        tgt = X0[ids].copy()
        tgt[onB, 2] = np.where(edge[onB], z_edge, z_rest)
        x, v, st = sim.step(x, v, None, None, None, tgt)
        assert st.converged and st.body_gap == 0.0 and st.penalty_iterations == 0
        kappa = kappa or st.barrier_stiffness
        assert st.barrier_stiffness == kappa
    np.testing.assert_array_equal(x[ids], tgt)
    assert self_intersecting_frames(x[None], FF) == [0]  # the prescribed strips cross (input)
    assert self_intersecting_frames(x[None], FF, prescribed=bnd) == []  # nothing else does


def test_candidates_of_a_segment_cover_its_points_and_give_the_static_barrier_set():
    """CandidateScene.covers: a point on the last CCD segment (inside its per-vertex box) has
    the same barrier set from the segment's candidates as from a fresh static build; a point
    off the segment is not covered."""
    V, F = grid(6, 0.3, z=0.1005)
    B, BF = sphere()
    sim = ClothSim(V, F, Material(), SimSettings())
    sim.prepare(B, BF)
    X0 = np.vstack([V, B])
    X1 = X0.copy()
    X1[: len(V), 2] -= 0.002  # the cloth comes down towards the sphere
    scene = sim.scene
    alpha = scene.collision_free_stepsize(X0, X1)
    X = X0 + 0.5 * alpha * (X1 - X0)
    assert scene.covers(X) and scene.covers(X0) and not scene.covers(X1 + 1e-3)
    seg = scene.collisions_at(X)
    pairs_seg = sorted(tuple(c.vertex_ids(scene.mesh.edges, scene.mesh.faces)) for c in seg)
    assert len(pairs_seg) > 0
    scene.prepare_static(X)
    assert scene.covers(X) and not scene.covers(X0)
    stat = scene.collisions_at(X)
    assert sorted(tuple(c.vertex_ids(scene.mesh.edges, scene.mesh.faces)) for c in stat) == pairs_seg


def test_energy_memo_is_used_only_while_nothing_e_depends_on_changed():
    """linesearch.EnergyMemo returns the stored E only for the same iterate, barrier set,
    barrier potential (κ), friction lag and penalty state."""
    from physavatar.sim.linesearch import EnergyMemo

    V, F = grid(4, 0.3, z=0.1005)
    B, BF = sphere()
    sim = ClothSim(V, F, Material(), SimSettings())
    sim.prepare(B, BF)
    X = np.vstack([V, B])
    sim.scene.prepare_static(X)
    sim.scene.collisions_at(X)
    memo = EnergyMemo()
    memo.set(EnergyMemo.key(sim, X, False), 1.5)
    assert memo.get(EnergyMemo.key(sim, X, False)) == 1.5
    assert memo.get(EnergyMemo.key(sim, X.copy(), False)) is None  # another iterate
    assert memo.get(EnergyMemo.key(sim, X, True)) is None  # penalty mode
    sim.barrier.set_stiffness(2.0 * sim.barrier.scale + 1.0)  # κ changed
    assert memo.get(EnergyMemo.key(sim, X, False)) is None
    memo.set(EnergyMemo.key(sim, X, False), 2.5)
    sim.scene.prepare_static(X)  # the barrier set is rebuilt
    sim.scene.collisions_at(X)
    assert memo.get(EnergyMemo.key(sim, X, False)) is None


def test_a_penalty_phase_that_stalls_gives_up_early():
    """The plates above with the default budget (40 penalty iterations) and ClothSim.stall_exit
    (simulate sets it when a retry in shorter steps would follow): once the plates' gap to their
    poses shrinks by less than stall_progress in stall_window iterations (the cloth has no room)
    the step gives up at once instead of spending the budget (the CMU walk's frame 99 spent 40
    iterations, 30-100 s, on each of its pinched steps), keeping the intersection-free state it
    reached. Without stall_exit the budget is spent, as before."""
    V, F = grid(5, 0.1)
    P, PF = grid(3, 0.2)
    plates_t = np.vstack([P + [0, 0, 0.01], P + [0, 0, -0.01]])
    plates_t1 = np.vstack([P + [0, 0, -0.01], P + [0, 0, 0.01]])
    Fb = np.vstack([PF, PF + len(P)])
    its = {}
    for exit_early in (False, True):
        sim = ClothSim(V, F, Material(), SimSettings(friction=0.0, lag_radius=0.0), [])  # the whole body lags
        sim.stall_exit = exit_early
        x, v, st = sim.step(V, np.zeros_like(V), plates_t, plates_t1, Fb)
        assert not st.converged and st.body_gap > 1e-3
        assert not sim.scene.has_intersections(np.vstack([x, sim._body_lag[1]]))
        its[exit_early] = st.penalty_iterations
    assert its[False] == 40 and ClothSim.stall_window < its[True] < 20


def test_a_pinch_holds_back_only_the_body_near_it():
    """Confined lag (sim.lag, SimSettings.lag_radius): the two plates above close through the
    cloth while a third plate, 2 m away, moves 2 cm. The penalty phase gives up (no room
    between the first two); with lag_radius 0 the far plate lags too (one line-search step
    length moves every prescribed vertex), with the default it reaches its pose exactly
    while the pinching plates keep their lag, and the state stays intersection-free."""
    V, F = grid(5, 0.1)
    P, PF = grid(3, 0.2)
    far = P + [2.0, 0.0, 0.0]
    plates_t = np.vstack([P + [0, 0, 0.01], P + [0, 0, -0.01], far])
    plates_t1 = np.vstack([P + [0, 0, -0.01], P + [0, 0, 0.01], far + [0, 0, 0.02]])
    Fb = np.vstack([PF, PF + len(P), PF + 2 * len(P)])
    gaps = {}
    for r in (0.0, SimSettings().lag_radius):
        sim = ClothSim(V, F, Material(), SimSettings(friction=0.0, lag_radius=r), [])
        x, v, st = sim.step(V, np.zeros_like(V), plates_t, plates_t1, Fb)
        body = sim._body_lag[1]
        assert st.body_gap > 5e-3 and not sim.scene.has_intersections(np.vstack([x, body]))
        gaps[r] = np.linalg.norm(body - plates_t1, axis=1)
        assert st.body_gap == pytest.approx(gaps[r].max())
    assert gaps[0.0][2 * len(P):].min() > 5e-3  # the whole body lags
    assert np.all(gaps[SimSettings().lag_radius][2 * len(P):] == 0.0)  # only the pinch lags
    assert gaps[SimSettings().lag_radius][: 2 * len(P)].min() > 5e-3


def test_contact_preview_pairs_are_ipctks_own_set_at_the_larger_distance():
    """The contact preview (Barrier.preview_hessian, SimSettings.contact_preview) takes the pairs
    within d̂₂ ≤ 2 d̂ from the candidates the solver already has (a CCD segment's, each box
    inflated by d̂): at every point of the segment they must be the set ipctk builds itself
    at d̂₂ with its own broad phase, and the preview Hessian that set's barrier Hessian."""
    from physavatar.sim.contact import Barrier

    V, B, scene, X0, X1, alpha = sheet_into_sphere(5, 0.1006, 0.002)
    assert 0 < alpha < 1
    d2 = 2e-3
    potential = ipctk.BarrierPotential(d2, 3.0)
    barrier = Barrier(scene, 3.0)
    beyond = False
    for t in (0.0, 0.5 * alpha, alpha):
        Xt = X0 + t * (X1 - X0)
        scene.prepare_segment(X0, X1)
        near = len(scene.collisions_at(Xt))
        c = scene.preview_collisions(Xt, d2)
        H = barrier.preview_hessian(Xt, d2).matrix
        ref = ipctk.NormalCollisions()
        ref.build(scene.mesh, Xt, d2)
        assert len(c) == len(ref) >= near > 0
        beyond |= len(c) > near
        assert potential(c, scene.mesh, Xt) == pytest.approx(potential(ref, scene.mesh, Xt), rel=1e-12)
        H_ref = potential.hessian(ref, scene.mesh, Xt, ipctk.PSDProjectionMethod.CLAMP)
        assert abs(H - H_ref).max() <= 1e-10 * abs(H_ref).max()
    assert beyond  # the preview did hold pairs beyond d̂


def test_contact_preview_changes_the_path_not_the_solution():
    """The preview's matrix (SimSettings.contact_preview) only changes the Newton directions: each
    step, from the same state, ends where the plain solve ends, to the Newton tolerance (a
    plane rising into a cloth pinned at its corners), in fewer Newton iterations here."""
    V, F = grid(9, 0.3)
    B, BF = cloth_grid.grid(5, 0.2, -0.012, center=True)
    pins = [0, 8, 72, 80]
    m = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5)
    sims = [ClothSim(V, F, m, SimSettings(damping_mass=0.5, newton_tol=1e-6, contact_preview=r), pins)
            for r in (0.0, 1.25)]
    x, v = V.copy(), np.zeros_like(V)
    its, diffs, changed = np.zeros(2, dtype=int), [], False
    for t in range(6):
        b0, b1 = B + [0, 0, 0.01 * t], B + [0, 0, 0.01 * (t + 1)]
        sims[1].set_state(sims[0].get_state())
        out = [sim.step(x, v, b0, b1, BF, V[pins]) for sim in sims]
        for k, (xk, _, st) in enumerate(out):
            assert st.converged
            assert not ipctk.has_intersections(sims[k].scene.mesh, np.vstack([xk, b1]))
            its[k] += st.newton_iterations
        diffs.append(np.abs(out[0][0] - out[1][0]).max())
        changed |= not np.array_equal(out[0][0], out[1][0])
        x, v = out[0][0], out[0][1]
    assert x[:, 2].max() > 0.03  # the plane did push the cloth up
    assert changed and max(diffs) < 1e-6, diffs
    assert its[1] < its[0], its


def test_contact_preview_beyond_the_candidates_reach_is_refused():
    with pytest.raises(ValueError, match="contact_preview"):
        SimSettings(contact_preview=2.5)



def test_release_of_the_carried_cloth_changes_the_start_not_the_solution():
    """SimSettings.follow_release moves the carried cloth off the body back toward its inertial
    prediction (CCD-clipped, kept when E is lower): a sphere rising under a stiff cloth, so every
    step after the first is carried. Each step, from the same state, ends where the step from the
    plain carry ends, to the Newton tolerance, except the first contact step, where the cloth
    settles on another facet of the faceted sphere (0.6 mm away, also with a 1e-7 `max`
    tolerance: a nearby minimum, as in the contact preview's and the follow_body tests). Every
    state is intersection-free."""
    from physavatar.sim.start import release_weight

    w = release_weight([0.0, 2e-3, 6e-3, 1e-2, 0.05], 1e-3, 0.01)
    assert np.allclose(w, [0.0, 0.0, 0.5, 1.0, 1.0])  # none within 2 d̂, all from the release distance
    m = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-2)
    V, F = grid(7, 0.3, z=0.0)
    B0, BF = sphere()
    B0 = B0 + np.array([0, 0, -0.13])
    pins = [0, 6, 42, 48]
    sims = [ClothSim(V, F, m, SimSettings(damping_mass=0.5, newton_tol=1e-6, friction=0.0, follow_body=0.05,
                                          follow_release=r), pins) for r in (0.0, 0.02)]
    starts = []

    def recording(start):  # the start of each step's Newton solve
        def wrapped(*args):
            sv = start(*args)
            starts.append(sv.X.copy())
            return sv
        return wrapped

    for sim in sims:
        sim._start = recording(sim._start)
    x, v = V.copy(), np.zeros_like(V)
    diffs, changed, follows = [], 0, 0
    for t in range(6):
        b0, b1 = B0 + np.array([0, 0, 0.012 * t]), B0 + np.array([0, 0, 0.012 * (t + 1)])
        sims[1].set_state(sims[0].get_state())
        out = [sim.step(x, v, b0, b1, BF, V[pins]) for sim in sims]
        for k, (xk, _, st) in enumerate(out):
            assert st.converged
            assert not ipctk.has_intersections(sims[k].scene.mesh, np.vstack([xk, b1]))
            follows += st.body_follows
        diffs.append(np.abs(out[0][0] - out[1][0]).max())
        changed += not np.array_equal(starts[-2], starts[-1])
        x, v = out[0][0], out[0][1]
    assert x[:, 2].max() > 0.01 and follows >= 8  # the sphere did push the cloth, which was carried
    assert changed >= 3  # the release moved the start
    assert sorted(diffs)[-2] < 1e-6 and max(diffs) < 1e-3, diffs
