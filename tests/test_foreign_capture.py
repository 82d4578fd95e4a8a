"""The foreign-capture generator (benchmarks/foreign/): NVIDIA Newton's VBD cloth driver and the
capture writer. Skips when newton is not installed (`pip install physavatar[foreign]`).

Warp compiles Newton's kernels on first use (a few minutes, cached in ~/.cache/warp); with the
cache warm these tests take seconds.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("newton")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from foreign.newton_cloth import ClothOnBody, Fabric, NewtonSettings

G = 9.81


def square(n=9, size=0.3, z=1.0):
    xs = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(xs, xs)
    V = np.stack([X.ravel(), Y.ravel(), np.full(n * n, z)], 1)
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return V, np.array(F)


def sphere(radius, center, subdivisions=2):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions, radius=radius)
    return np.asarray(s.vertices) + np.asarray(center), np.asarray(s.faces)


def test_free_fall_matches_gravity_before_contact():
    """No contact, no pins: every particle falls as VBD's implicit Euler does: after n steps of h,
    z drop = g h² n(n+1)/2 exactly (membrane forces vanish for a rigid translation), which is
    0.5 g t² to O(h)."""
    V, F = square()
    st = NewtonSettings(substeps=5, iterations=5)
    sim = ClothOnBody(V, F, [], None, None, Fabric(), st)
    dt = 0.04
    for _ in range(3):
        x = sim.advance(dt)
    n, h = 15, dt / 5
    drop = 1.0 - x[:, 2]
    assert np.allclose(drop, G * h * h * n * (n + 1) / 2, rtol=1e-3)
    t = n * h
    assert abs(drop.mean() - 0.5 * G * t * t) < 0.1 * 0.5 * G * t * t
    assert np.allclose(x[:, :2], V[:, :2], atol=1e-6)  # no sideways drift


def test_drop_on_sphere_rests_on_top_without_crossing():
    """A square dropped on a sphere mesh drapes over it: finite, the centre rests on the top at
    the contact radius, the corners hang below it, and no cloth edge crosses the sphere."""
    from physavatar.geometry.intersect import count_intersections

    V, F = square(n=11, size=0.4, z=0.9)
    SV, SF = sphere(0.1, (0.0, 0.0, 0.7), 3)
    st = NewtonSettings(substeps=10, iterations=8)
    sim = ClothOnBody(V, F, [], SV, SF, Fabric(), st)
    for _ in range(10):
        x = sim.advance(0.04, SV)
    assert np.isfinite(x).all()
    centre = x[len(V) // 2]
    assert abs(centre[2] - (0.8 + st.radius)) < 3e-3, centre
    assert x[0, 2] < centre[2] - 0.05  # corners sag
    assert count_intersections(x, F, SV, SF) == 0


def test_pinned_edge_sags_by_a_small_strain():
    """A strip pinned along one edge swings down and hangs below its pins (the free edge lowest),
    while its edges stretch by no more than the order of ρ g L / μ (0.2 % here; 3 % allowed for
    the swing)."""
    V, F = square(n=9, size=0.2, z=1.0)
    pinned = np.flatnonzero(np.isclose(V[:, 1], V[:, 1].max()))
    fab = Fabric(density=0.2, tri_ke=200.0, tri_ka=100.0, edge_ke=1e-4)
    sim = ClothOnBody(V, F, pinned, None, None, fab, NewtonSettings(substeps=10, iterations=10))
    for _ in range(25):
        x = sim.advance(0.04, None, V[pinned])
    assert np.isfinite(x).all()
    assert np.allclose(x[pinned], V[pinned], atol=1e-6)
    free = np.isclose(V[:, 1], V[:, 1].min())
    assert (x[free, 2] < 1.0 - 0.1).all()  # hangs down
    assert x[free, 2].mean() < x[~free & ~np.isin(np.arange(len(V)), pinned), 2].mean()
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    strain = np.linalg.norm(x[E[:, 0]] - x[E[:, 1]], axis=1) / np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1) - 1
    assert np.percentile(np.abs(strain), 95) < 0.03, np.percentile(np.abs(strain), 95)


def test_fabric_mapping_is_the_plane_stress_lame_pair():
    f = Fabric.from_physical(0.2, 30.0, 2e-5, 0.25, 0.02)
    assert f.tri_ke == pytest.approx(30.0 / 2.5)
    assert f.tri_ka == pytest.approx(30.0 * 0.25 / (1 - 0.0625))
    assert f.edge_ke == pytest.approx(3 * 2e-5 / (np.sqrt(3) / 2 * 0.02))


def test_capture_writer_output_loads(tmp_path):
    """A tiny foreign capture is accepted by physavatar's loader, with ground truth consistent."""
    from foreign.capture import ForeignConfig, build

    from physavatar.capture import load_capture
    from physavatar.data.ground_truth import ground_truth_problems

    cfg = ForeignConfig(name="t", size=32, cameras=3, heldout_views=1, frames=3, heldout_frames=2, settle_frames=0,
                        substeps=2, iterations=3, spp=1, texture_size=128, edge=0.05)
    root = build(tmp_path / "cap", cfg, say=lambda s: None)
    cap = load_capture(root, deep=True)
    assert cap.frames == [0, 1, 2] and len(cap.cameras) == 3
    assert ground_truth_problems(cap) == []
    gt = np.load(root / "ground_truth" / "meshes.npz")
    assert gt["vertices"].shape == (3, len(cap.template.vertices), 3)
    assert np.allclose(gt["vertices"][0], cap.template.vertices, atol=1e-5)
    assert not (root / "ground_truth" / "material.json").exists()
    assert (root / "ground_truth" / "heldout" / "images").is_dir()
    assert np.load(root / "ground_truth" / "texture_linear.npy").shape == (128, 128, 3)
    # pinned garment vertices are flagged as boundary
    assert cap.template.boundary[cap.template.labels > 0].any()


def test_damped_settle_brings_the_drape_to_rest():
    """A strip pinned along one edge, released flat, swings down. With the fabric's own (nearly
    nil) damping it still swings after the settle frames; with the settle's drag (velocities × 0.7
    per frame) it hangs at rest: its last settle frame moves < 1/10 of the undamped one's, and the
    next free frame (no drag) moves < 0.3 mm, so frame 0 of a capture is a rest state."""
    from foreign.newton_cloth import simulate_sequence

    V, F = square(n=7, size=0.2, z=1.0)
    pinned = np.flatnonzero(np.isclose(V[:, 1], V[:, 1].max()))
    fab = Fabric(density=0.2, tri_ke=200.0, tri_ka=100.0, edge_ke=1e-4, tri_kd=1e-6, edge_kd=1e-6)
    st = NewtonSettings(substeps=5, iterations=10)
    pins = np.repeat(V[pinned][None], 2, 0)
    drift, x = {}, {}
    for keep in (1.0, 0.7):
        info = {}
        x[keep] = simulate_sequence(V, F, pinned, pins, [None, None], None, 25.0, fab, st, settle_frames=40,
                                    settle_damping=keep, info=info)
        drift[keep] = info["settle_drift_mm"]
    assert drift[1.0] > 1.0, drift  # undamped: still swinging by more than 1 mm per frame
    assert drift[0.7] < drift[1.0] / 10, drift
    assert np.linalg.norm(x[0.7][1] - x[0.7][0], axis=1).mean() < 0.3e-3  # free frame after the settle: at rest
    free = np.isclose(V[:, 1], V[:, 1].min())
    assert (x[0.7][0][free, 2] < 1.0 - 0.15).all()  # it hangs down
