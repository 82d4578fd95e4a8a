"""Sub-steps on the body's own path (sim.simulate ``collider_between``): a frame split into n
steps takes its in-between bodies from the path given (its attached targets stay on the straight
line between the frames' targets), meets the frames bit for bit, and without one steps along the
straight line exactly as before."""

import numpy as np
import pytest
import trimesh

from cloth_grid import grid
from physavatar.sim import Material, SimSettings, simulate
from physavatar.sim.solver import ClothSim

MAT = Material(density=0.15, stretch_stiffness=30.0, bend_stiffness=1e-5)


def turn(V, angle):
    c, s = np.cos(angle), np.sin(angle)
    return V @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T


def paddle():
    """A paddle about the z axis: a 2-cm thick box from 5 to 30 cm along x."""
    m = trimesh.creation.box(extents=[0.25, 0.02, 0.1])
    return np.asarray(m.vertices) + [0.175, 0.0, 0.0], np.asarray(m.faces)


def curtain():
    """A 10 × 20 cm curtain in the plane x = 0.26, pinned along its top edge."""
    V, F = grid(5, 0.1)
    V = np.c_[np.full(len(V), 0.26), V[:, 0] - 0.05, 2 * V[:, 1] - 0.1]
    return V, F, np.flatnonzero(V[:, 2] > 0.099)


def test_a_paddle_turning_a_quarter_turn_in_a_frame_sweeps_the_cloth_its_chord_misses():
    """The paddle turns from −45° to +45° about z in one frame, simulated in 8 steps. Its tip
    (r = 0.3 m) passes x = 0.3 on its arc, through the curtain at x = 0.26, but only x = 0.21
    on the chord between the two frames: stepped along the straight line the curtain is never
    touched (it sags by a millimetre under its own weight); stepped along the turn given as
    ``collider_between`` (a rigid rotation, analytic) it is swept out past the tip's radius
    reach, as the body really moves."""
    B, BF = paddle()
    frames = np.stack([turn(B, -np.pi / 4), turn(B, np.pi / 4)])
    V, F, pins = curtain()
    between = lambda f, s: np.stack([turn(B, -np.pi / 4 + (f - 1 + t) * np.pi / 2) for t in s])  # noqa: E731
    kw = dict(fps=25.0, substeps=8, settings=SimSettings(damping_mass=0.5))
    X_line = simulate(V, F, MAT, frames, BF, pins, None, **kw)
    X_turn = simulate(V, F, MAT, frames, BF, pins, None, collider_between=between, **kw)
    moved_line = np.linalg.norm(X_line[1] - V, axis=1).max()
    radial = np.linalg.norm(X_turn[1][:, :2], axis=1)
    assert moved_line < 2e-3 and np.linalg.norm(X_line[1][:, :2], axis=1).max() < 0.27  # its own sag only
    assert radial.max() > 0.29  # swept out to the tip's reach
    assert np.linalg.norm(X_turn[1] - V, axis=1).max() > 0.05


@pytest.fixture
def recorded(monkeypatch):
    """The bodies and targets each implicit step was given."""
    steps = []
    real = ClothSim.step

    def step(self, x, v, body_t, body_t1, body_faces, boundary_targets=None, history=None):
        steps.append((np.array(body_t), np.array(body_t1), None if boundary_targets is None else np.array(boundary_targets)))
        return real(self, x, v, body_t, body_t1, body_faces, boundary_targets, history)

    monkeypatch.setattr(ClothSim, "step", step)
    return steps


def test_sub_steps_take_their_bodies_from_the_path_given_and_their_targets_from_the_chord(recorded):
    """With ``collider_between``, step k of n is given the path's bodies at k/n and (k+1)/n
    (sim.simulate.between_bodies: the frames themselves bit for bit at the ends) and the attached
    targets on the straight line between the frames' targets, (1 − w)·t0 + w·t1 bit for bit
    (session 31: they no longer ride the in-between body); with n = 1 the path is never asked;
    without it, the straight line for both, bit for bit the formula before session 30."""
    B, BF = paddle()
    frames = np.stack([turn(B, 0.0), turn(B, 0.3), turn(B, 0.6)])
    V, F, pins = curtain()
    V = V + [0.2, 0.0, 0.0]  # out of reach: only the path given is checked here
    calls = []

    def between(f, s):
        calls.append((f, tuple(s)))
        return np.stack([turn(B, 0.3 * (f - 1 + t)) for t in s])

    targets = np.stack([turn(V[pins], a) for a in (0.0, 0.3, 0.6)])
    targets[2] += 0.001  # a target corrected after riding
    kw = dict(fps=25.0, substeps=4, settings=SimSettings(damping_mass=0.5))
    simulate(V, F, MAT, frames, BF, pins, targets, collider_between=between, **kw)
    assert [c[0] for c in calls] == [1, 2] and calls[0][1] == (0.0, 0.25, 0.5, 0.75, 1.0)
    assert len(recorded) == 8
    for k, (b0, b1, tg) in enumerate(recorded):
        f, j = 1 + k // 4, k % 4
        a0, a1, w = 0.3 * (f - 1 + j / 4), 0.3 * (f - 1 + (j + 1) / 4), (j + 1) / 4
        np.testing.assert_allclose(b0, turn(B, a0), atol=1e-12)
        np.testing.assert_allclose(b1, turn(B, a1), atol=1e-12)
        assert np.array_equal(tg, (1 - w) * targets[f - 1] + w * targets[f])
        if j == 1:  # half-way: the chord is r (1 − cos 0.15) inside the turn (r = 0.46 m: 5.2 mm)
            sag = np.linalg.norm(turn(V[pins], a1)[:, :2], axis=1) - np.linalg.norm(tg[:, :2], axis=1)
            np.testing.assert_allclose(sag, np.linalg.norm(V[pins, :2], axis=1) * (1 - np.cos(0.15)), atol=1e-3)
    assert np.array_equal(recorded[3][1], frames[1]) and np.array_equal(recorded[4][0], frames[1])
    assert np.array_equal(recorded[7][1], frames[2]) and np.array_equal(recorded[7][2], targets[2])

    recorded.clear(), calls.clear()
    simulate(V, F, MAT, frames, BF, pins, targets, collider_between=between, **(kw | {"substeps": 1}))
    assert calls == [] and len(recorded) == 2

    recorded.clear()
    simulate(V, F, MAT, frames, BF, pins, targets, **kw)
    for k, (b0, b1, tg) in enumerate(recorded):
        f, j = 1 + k // 4, k % 4
        w0, w1 = j / 4, (j + 1) / 4
        assert np.array_equal(b0, (1 - w0) * frames[f - 1] + w0 * frames[f])
        assert np.array_equal(b1, (1 - w1) * frames[f - 1] + w1 * frames[f])
        assert np.array_equal(tg, (1 - w1) * targets[f - 1] + w1 * targets[f])


def test_a_garment_on_a_skinned_path_keeps_its_attached_targets_on_the_chord(recorded):
    """garment_sim.simulate_on_body with ``between`` (as `simulate --skinned-between` calls it):
    the in-between bodies are the turn given, the attached vertices' targets the straight line
    between the frames' targets (garment_sim.boundary_targets), bit for bit, not their ride on the
    turning body — which half-way through a step of the turn lies r (1 − cos θ/2) further out."""
    from physavatar.garment import attachment_positions
    from physavatar.garment_sim import GarmentPart, boundary_targets, simulate_on_body

    B, BF = paddle()
    frames = np.stack([turn(B, a) for a in (0.0, 0.3, 0.6)])
    V, F, pins = curtain()
    V = V + [0.2, 0.0, 0.0]  # hanging beside the paddle's tip, out of its reach
    part = GarmentPart(np.arange(len(V)), V, F, pins)
    settings = SimSettings(damping_mass=0.5)
    targets, report = boundary_targets(part, frames, BF, settings.dhat)
    np.testing.assert_allclose(targets, np.stack([turn(V[pins], a) for a in (0.0, 0.3, 0.6)]), atol=1e-9)

    def between(f, s):
        return np.stack([turn(B, 0.3 * (f - 1 + t)) for t in s])

    simulate_on_body(part, frames, BF, MAT, 25.0, settings, substeps=4, between=between)
    assert len(recorded) == 8
    for k, (b0, b1, tg) in enumerate(recorded):
        f, j = 1 + k // 4, k % 4
        a1, w = 0.3 * (f - 1 + (j + 1) / 4), (j + 1) / 4
        np.testing.assert_allclose(b1, turn(B, a1), atol=1e-12)  # the body on the turn
        assert np.array_equal(tg, (1 - w) * targets[f - 1] + w * targets[f])  # the targets on the chord
        if j == 1:  # the ride would be 5 mm out
            ride = attachment_positions(report["attachment"], b1)
            assert np.linalg.norm(ride - tg, axis=1).min() > 4e-3


def test_a_run_on_the_skinned_path_resumes_with_the_same_frames():
    """The skinned in-betweens (the default since session 31) depend on the frame and the step
    alone, so a run resumed from a frame's checkpoint writes the later frames bit for bit as the
    uninterrupted run (here with the curtain swept by the turning paddle, in contact)."""
    B, BF = paddle()
    angles = [-np.pi / 4, -np.pi / 8, 0.0, np.pi / 8]
    frames = np.stack([turn(B, a) for a in angles])
    V, F, pins = curtain()
    between = lambda f, s: np.stack([turn(B, -np.pi / 4 + (f - 1 + t) * np.pi / 8) for t in s])  # noqa: E731
    kw = dict(fps=25.0, substeps=2, max_substeps=8, settings=SimSettings(damping_mass=0.5), collider_between=between)
    saved = {}
    whole = simulate(V, F, MAT, frames, BF, pins, None, on_frame=lambda ck, r: saved.setdefault(ck.frame, ck), **kw)
    resumed = simulate(V, F, MAT, frames, BF, pins, None, resume=saved[1], **kw)
    assert np.isnan(resumed[0]).all() and np.array_equal(resumed[1:], whole[1:])
    assert np.linalg.norm(whole[-1] - V, axis=1).max() > 0.01  # the paddle reached the curtain
