"""Threaded candidate builds (SimSettings.candidate_threads): the barrier set and everything
summed over it are the same bits whatever order the candidates come in (contact.canonical_order;
docs/simulation.md "Session 32")."""

import ipctk
import numpy as np
from cloth_grid import grid
from test_sim_solver import sphere

from physavatar.sim import Material, SimSettings, simulate
from physavatar.sim.contact import ContactScene, canonical_order

KINDS = ("vv", "ev", "ee", "fv")


def crumpled_sheet_on_sphere(seed=0):
    """A 24×24 sheet with 3-mm noise resting on the test sphere, self-contact on, moved by a
    random segment: (scene, X0, X1), with thousands of cloth–cloth and cloth–body candidates."""
    rng = np.random.default_rng(seed)
    V, F = grid(24, 0.3, z=0.1005, center=True)
    V = V + rng.normal(scale=3e-3, size=V.shape) * [1.0, 1.0, 0.2]
    B, BF = sphere()
    scene = ContactScene(V, F, B, BF, dhat=5e-3, self_contact=True)
    scene.canonical = True  # what SimSettings.candidate_threads ≥ 1 sets (ClothSim)
    X0 = np.vstack([V, B])
    X1 = X0.copy()
    X1[: len(V)] += rng.normal(scale=2e-3, size=V.shape)
    return scene, X0, X1


def barrier_bits(scene, X):
    """The ids of every collision at X, in order, and the barrier's energy, gradient and Hessian."""
    c = scene.collisions_at(X)
    E, F = scene.mesh.edges, scene.mesh.faces
    ids = [[tuple(x.vertex_ids(E, F)) for x in getattr(c, k + "_collisions")] for k in KINDS]
    b = ipctk.BarrierPotential(scene.dhat, 1.0)
    H = b.hessian(c, scene.mesh, X, ipctk.PSDProjectionMethod.CLAMP).tocsr()
    return ids, b(c, scene.mesh, X), b.gradient(c, scene.mesh, X), H


def same_bits(a, b):
    return (a[0] == b[0] and a[1] == b[1] and np.array_equal(a[2], b[2])
            and np.array_equal(a[3].indptr, b[3].indptr) and np.array_equal(a[3].indices, b[3].indices)
            and np.array_equal(a[3].data, b[3].data))


def test_barrier_set_is_the_same_bits_for_any_candidate_order():
    """The candidates of a segment listed in shuffled orders (what a threaded build does) give
    the barrier set of the one-thread build, in the same order, and the same energy, gradient
    and Hessian bits; so do builds on two threads."""
    threads = ipctk.get_num_threads()
    ipctk.set_num_threads(1)  # the solver's sums (ClothSim.step): ipctk's threaded ones are not ordered
    try:
        check_candidate_orders()
    finally:
        ipctk.set_num_threads(threads)


def check_candidate_orders():
    scene, X0, X1 = crumpled_sheet_on_sphere()
    X = X0 + 0.5 * (X1 - X0)
    scene.prepare_segment(X0, X1)
    cand = scene.candidates
    # the candidates as ids (ipctk's list items point into the candidates' own storage)
    lists = {"ee": [(c.edge0_id, c.edge1_id) for c in cand.ee_candidates],
             "fv": [(c.face_id, c.vertex_id) for c in cand.fv_candidates]}
    assert not cand.vv_candidates and not cand.ev_candidates  # (a triangle mesh: ee and fv only)
    assert len(lists["ee"]) > 2000 and len(lists["fv"]) > 500
    make = {"ee": ipctk.EdgeEdgeCandidate, "fv": ipctk.FaceVertexCandidate}
    ref = barrier_bits(scene, X)
    assert sum(map(len, ref[0])) > 300 and len(ref[0][2]) > 50  # edge–edge pairs among them
    rng = np.random.default_rng(1)
    for _ in range(3):
        for k, items in lists.items():
            setattr(cand, k + "_candidates", [make[k](*items[i]) for i in rng.permutation(len(items))])
        scene._collisions_at = None  # a new set from the shuffled candidates
        assert same_bits(barrier_bits(scene, X), ref)
    # without the canonical order the shuffled set is another order (what this test guards)
    raw = ipctk.NormalCollisions()
    raw.build(cand, scene.mesh, X, scene.dhat, scene.dmin)
    assert [x.edge0_id for x in raw.ee_collisions] != [x.edge0_id for x in scene.collisions.ee_collisions]
    canonical_order(raw)
    assert [x.edge0_id for x in raw.ee_collisions] == [x.edge0_id for x in scene.collisions.ee_collisions]
    scene.build_threads = 2
    for _ in range(3):
        scene.prepare_segment(X0, X1)
        assert same_bits(barrier_bits(scene, X), ref)


def test_candidate_threads_give_bit_identical_trajectories():
    """A cloth with self-contact pushed by a moving sphere: one and two candidate-build threads
    (with two CCD threads too) give the same trajectory, bit for bit (0, the default, keeps the
    candidates' own order: the code before session 32)."""
    V, F = grid(12, 0.3, z=0.11, center=True)
    B, BF = sphere()
    seq = np.stack([B + np.array([0.006 * t, 0, 0.004 * t]) for t in range(6)])
    runs = [simulate(V, F, Material(), seq, BF, fps=25.0,
                     settings=SimSettings(candidate_threads=k, ccd_threads=c, self_contact=True))
            for k, c in ((1, 1), (2, 1), (2, 2))]
    assert np.array_equal(runs[0], runs[1]) and np.array_equal(runs[0], runs[2])


def test_a_negative_candidate_thread_count_is_refused():
    import pytest

    with pytest.raises(ValueError, match="candidate_threads -1"):
        SimSettings(candidate_threads=-1)
    assert SimSettings(candidate_threads=2).candidate_threads == 2
