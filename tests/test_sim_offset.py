"""The cloth's contact thickness (Material.contact_offset, ipctk's d_min): cloth settles at it on a
plane (its distance is its height), the exact gradients hold with it (central differences), and
the estimate from a template finds a resting band and ignores a designed clearance."""

import dataclasses

import cloth_grid
import numpy as np
import pytest

from physavatar.sim import ClothSim, Material, SimSettings, preset
from physavatar.sim.offset import estimate_contact_offset


def plane(size=1.0, z=0.0):
    """A square floor of two triangles at height z, facing up."""
    V = np.array([[-size, -size, z], [size, -size, z], [size, size, z], [-size, size, z]])
    return V, np.array([[0, 1, 2], [0, 2, 3]])


def settle_on_plane(material, drop=0.008, steps=40):
    V, F = cloth_grid.grid(7, 0.3, z=drop, center=True)
    B, BF = plane()
    sim = ClothSim(V, F, material, SimSettings(dt=0.04, damping_mass=5.0), [])
    x, v = V.copy(), np.zeros_like(V)
    for _ in range(steps):
        x, v, st = sim.step(x, v, B, B, BF)
        assert st.converged and np.all(np.isfinite(x))
    assert np.abs(v).max() < 1e-3  # at rest
    return x[:, 2]


@pytest.mark.parametrize("offset", [0.0, 0.003, 0.006])
def test_cloth_rests_on_a_plane_at_the_contact_offset(offset):
    """The height of cloth lying flat on a floor is its distance to it: within the barrier's
    reach (d_min, d_min + d̂) of the offset, d̂ = 1 mm."""
    z = settle_on_plane(dataclasses.replace(preset("cotton"), contact_offset=offset))
    dhat = SimSettings().dhat
    assert z.min() > offset
    assert z.max() < offset + dhat
    assert z.max() - z.min() < 0.2 * dhat  # flat on the floor


def test_settings_dmin_overrides_the_material():
    m = dataclasses.replace(preset("cotton"), contact_offset=0.003)
    V, F = cloth_grid.grid(3, 0.1)
    assert ClothSim(V, F, m, SimSettings()).dmin == 0.003
    assert ClothSim(V, F, m, SimSettings(dmin=0.005)).dmin == 0.005
    assert Material.from_dict(m.to_dict()).contact_offset == 0.003
    assert Material.from_dict({k: v for k, v in preset("cotton").to_dict().items()
                               if k != "contact_offset"}).contact_offset == 0.0  # older files


def test_exact_gradient_matches_central_fd_with_a_contact_offset():
    """The sensitivities through ipctk's d_min barrier (b(d² − d_min², (2 d_min + d̂) d̂)) against
    central differences of the simulator, as tests/test_physics.py does without an offset:
    frictionless within 1 % (measured 0.02 %); with friction 0.2 within 10 % (measured 7.6 % on
    κb: the lagged normal forces' dependence on θ, which the sensitivities leave out, is larger
    at the offset; 0.3 % without it)."""
    from test_physics import TIGHT, cloth_on_sphere, exact_and_central_fd

    from physavatar.geometry.closest import MeshQuery

    data = cloth_on_sphere()
    m = dataclasses.replace(preset("cotton"), contact_offset=0.003)
    for friction, tol in ((0.0, 0.01), (0.2, 0.1)):
        exact, fd, r = exact_and_central_fd(data, m, dataclasses.replace(TIGHT, friction=friction), 1e-3)
        assert r.positions[-1, :, 2].min() < -0.05  # draped over the sphere
        # the least cloth–sphere distance (cloth vertices to the sphere, sphere vertices to the cloth)
        d = min(MeshQuery(data.collider[0], data.collider_faces).closest(r.positions[-1])[0].min(),
                MeshQuery(r.positions[-1], data.faces).closest(data.collider[0])[0].min())
        assert 0.003 < d < 0.004  # it rests on the sphere at the offset
        assert np.all(np.abs(fd) > 1e-6)
        np.testing.assert_array_less(np.abs(exact - fd) / np.abs(fd), tol)


def test_offset_estimate_finds_the_resting_band_and_ignores_a_design_clearance():
    """A garment resting 6 mm on a floor over part of it, rising beyond (a drape, as NVIDIA
    Newton's cloth rests at its particle radius): offset 6 − d̂ = 5 mm. The same cloth placed at
    a clearance growing from 5 mm at one point (a design): no resting band, offset 0."""
    B, BF = plane()
    V, F = cloth_grid.grid(21, 0.4, center=True)
    rise = np.clip(V[:, 0], 0.0, None)  # flat for x < 0, rising beyond
    rest = V + np.c_[np.zeros((len(V), 2)), 0.006 + 0.3 * rise ** 1.5]
    offset, report = estimate_contact_offset(rest, F, B, BF)
    assert report["resting"] and offset == pytest.approx(0.005, abs=2e-4)
    r = np.linalg.norm(V[:, :2], axis=1)  # closest at one point, the clearance growing around it
    design = V + np.c_[np.zeros((len(V), 2)), 0.005 + 0.2 * r ** 1.2]
    offset, report = estimate_contact_offset(design, F, B, BF)
    assert not report["resting"] and offset == 0.0
    # capped at the least pair distance + d̂/2: the start needs a lift of at most about d̂
    poked = rest.copy()
    poked[len(V) // 4, 2] = 0.002
    offset, report = estimate_contact_offset(poked, F, B, BF)
    assert offset == pytest.approx(0.0025, abs=1e-4)


def test_lift_start_clears_every_pair_beyond_the_thickness():
    """A body vertex poking up under a cloth face that rests 6 mm above the floor (as Newton's
    drapes have them: its radius keeps only the cloth's vertices off): lift_start moves the
    cloth there, and only there, until every pair is beyond the clearance (ipctk's distances)."""
    from physavatar.sim.offset import lift_start, start_distance

    V, F = cloth_grid.grid(11, 0.2, z=0.006, center=True)
    B, BF = cloth_grid.grid(11, 0.2, z=0.0, center=True)
    B[60, 2] = 0.004  # under the middle of the cloth, 2 mm from its faces
    B[:, :2] += 0.01  # the body's vertices below the cloth's faces, not its vertices
    assert start_distance(V, F, B, BF) < 0.0021
    x, least = lift_start(V, F, B, BF, 0.0045)
    assert least >= 0.0045 and start_distance(x, F, B, BF) >= 0.0045
    moved = np.linalg.norm(x - V, axis=1) > 0
    assert 0 < moved.sum() <= 6  # the corners of the faces over the poke
    assert np.all(np.linalg.norm(V[moved, :2] - B[60, :2], axis=1) < 0.03)


def test_fit_physics_records_the_estimated_offset_and_simulations_keep_it(tmp_path):
    """The whole chain: a sequence of cloth resting 6 mm above a floor (as Newton's would) is fitted
    with the offset estimated from its first frame (6 − d̂ = 5 mm), material.json records it, and
    a simulation of the fitted material (no settings given) keeps the cloth that far off."""
    from physavatar.data.material import FittedMaterial
    from physavatar.sim import simulate
    from physavatar.stages.physics import run as fit_physics
    from physavatar.stages.physics.config import PhysicsConfig

    V, F = cloth_grid.grid(7, 0.3, z=0.006, center=True)
    B, BF = plane()
    T = 3
    np.savez(tmp_path / "seq.npz", vertices=np.repeat(V[None], T, 0), faces=F, body_vertices=np.repeat(B[None], T, 0),
             body_faces=BF, fps=25.0)
    fit_physics(tmp_path / "seq.npz", out=tmp_path / "fit", config=PhysicsConfig(window=3, iterations=1,
                                                                                 integrator="euler"))
    fitted = FittedMaterial.load(tmp_path / "fit" / "material.json")
    assert fitted.material.contact_offset == pytest.approx(0.005, abs=1e-5)
    assert fitted.start_state["contact_offset"]["resting"]
    x = simulate(V, F, fitted.material, np.repeat(B[None], 6, 0), BF, [], None, 25.0)
    assert np.all(x[-1][:, 2] > 0.005) and np.all(x[-1][:, 2] < 0.006)
