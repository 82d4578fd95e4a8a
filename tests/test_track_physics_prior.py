"""flow.carry "physics" (session 26): the flow lift's reference for the free garment is one step of
the cloth simulator, so where the views see the cloth it follows them and where they do not it
keeps the simulator's motion, checked against an independent simulation (simulate_on_body over
the whole clip, test_track's cloth over a rising ball)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from physavatar.camera import Camera, intrinsics, look_at
from physavatar.stages.track import TrackConfig
from physavatar.stages.track.flow import FlowObservation, FlowPrediction, FlowStart
from physavatar.stages.track.prediction import FrameStarts, PhysicsPrediction
from test_track import _cloth_over_ball, _cloth_over_ball_simulated


class _Skin:  # the capture's skinning, here the simulation's own frames (body and boundary)
    def __init__(self, frames):
        self.frames = frames

    def skin(self, i, points=None):
        return self.frames[i].copy()


class _Lift(FlowStart):  # FlowStart with given observations in place of the images' flow
    def __init__(self, flow, obs):
        super().__init__(flow, [], None, [], corrections=0)
        self.obs = obs
        self.flow.observe = lambda *a, **k: self.obs


def _starts(V, F, labels, boundary, frames, carry, obs, mat):
    from physavatar.garment_sim import split_template

    s = object.__new__(FrameStarts)
    cfg = TrackConfig()
    s.cfg = replace(cfg, flow=replace(cfg.flow, carry=carry))
    s.flow_cfg = s.cfg.flow
    s.frames, s._grey, s._masks, s.physics_frames = [0, 1, 2], {1: [], 2: []}, {}, {}
    s.mixed = s.use_flow = True
    s.skin, s.smooth = _Skin(frames), None
    s.skinned = (labels == 0) | boundary
    s.physics = PhysicsPrediction(V, F, labels, boundary, mat, 25.0) if carry == "physics" else None
    _, body_faces, part = split_template(V, F, labels, boundary)
    lift = FlowPrediction(F, ~s.skinned, part.vertex_ids[part.faces], rest=V, iso_weight=3.0, bend_weight=10.0,
                          collider_faces=body_faces)
    s.flow = _Lift(lift, obs)
    return s


def test_physics_carry_keeps_the_simulators_motion_where_no_view_sees_the_cloth():
    V, F, labels, boundary, bodies, body_ids, body_faces, part, mat, G, frames = _cloth_over_ball_simulated()
    truth = frames[2].copy()
    g = part.vertex_ids
    free = g[~np.isin(np.arange(len(g)), part.boundary)]
    # two cameras see the far half of the cloth (x > 0.05), 4 mm beyond where the simulation put
    # it: the images disagree with the physics there and decide
    seen = free[V[free, 0] > 0.05]
    truth[seen, 0] += 0.004
    cams = [Camera(n, 256, 256, intrinsics(256, 256, 40.0), look_at(eye, [0.0, 0.0, 0.12]))
            for n, eye in (("a", [0.1, -0.6, 0.9]), ("b", [0.7, 0.4, 0.6]))]
    obs = [FlowObservation(c, seen, c.project(truth[seen])[0]) for c in cams]
    unseen = free[V[free, 0] < -0.05]
    out = {}
    for carry in ("still", "velocity", "physics"):
        s = _starts(V, F, labels, boundary, frames, carry, obs, mat)
        out[carry] = np.asarray(s.start(2, frames[:2]), np.float64)
        np.testing.assert_allclose(out[carry][body_ids], bodies[2], atol=1e-6)
    sim2 = np.empty_like(V)
    sim2[g] = G[2]
    err = {c: np.linalg.norm(x[unseen] - sim2[unseen], axis=1).mean() for c, x in out.items()}
    assert s.physics_frames == {2: "stepped"}
    # unseen: the simulator's answer (its gravity and the ball's push) within a millimetre, where
    # "still" and constant velocity leave them centimetres or millimetres off
    assert err["physics"] < 1e-3 and min(err["still"], err["velocity"]) > 5e-3, err
    # seen: pulled toward the views (by the lift's balance of the data and its smoothness with the
    # unseen half: 1.3 mm of their 4 mm disagreement with the simulator, uniform over 14 vertices),
    # and nearer them than with "still", whose unseen half holds them back by centimetres
    x = out["physics"]
    toward = (x[seen, 0] - sim2[seen, 0]).mean()
    assert 0.001 < toward < 0.0045, toward
    assert np.linalg.norm(x[seen] - truth[seen], axis=1).mean() < 0.5 * np.linalg.norm(out["still"][seen] - truth[seen], axis=1).mean()


def test_a_physics_step_depends_on_its_arguments_alone():
    """A resumed tracking run starts a fresh PhysicsPrediction at the frame it resumes at. Its step
    must be the same bits as that of the predictor that ran every frame before: each call steps
    from the same sim state (the contact scene built on the template's body, the initial barrier
    stiffness), not from where the last call left the adaptive stiffness or the first call's body."""
    ball = _cloth_over_ball()[4]
    ball = np.concatenate([ball, ball[-1:] + [0.0, 0.0, 0.02]])  # the ball rises on into the cloth
    V, F, labels, boundary, bodies, body_ids, body_faces, part, mat, G, frames = _cloth_over_ball_simulated(ball)
    chained = PhysicsPrediction(V, F, labels, boundary, mat, 25.0)
    for k in range(2, len(frames)):
        a = chained(frames[k - 2], frames[k - 1], frames[k - 1], frames[k])
        b = PhysicsPrediction(V, F, labels, boundary, mat, 25.0)(frames[k - 2], frames[k - 1], frames[k - 1], frames[k])
        assert a is not None and np.array_equal(a, b), k


def test_a_fitted_contact_thickness_lifts_the_tracked_start_off_the_body():
    """fit-physics' material.json records a contact thickness (Material.contact_offset, ipctk's
    d_min: 3.07 mm on the foreign skirt). A tracked frame is not held that far off the body, and
    ipctk's barrier is undefined closer than d_min: the step raised "unable to project matrix onto
    positive semi-definite cone" on every frame of the skirt (session 29). The start is now lifted
    to the thickness first (sim.simulate.feasible_thickness), so the step runs and ends with every
    cloth-body pair at least d_min apart (ipctk's own distances, sim.offset.start_distance)."""
    from physavatar.sim.offset import start_distance

    ball = _cloth_over_ball()[4]
    ball = np.concatenate([ball, ball[-1:] + [0.0, 0.0, 0.02]])  # the ball rises on into the cloth
    V, F, labels, boundary, bodies, body_ids, body_faces, part, mat, G, frames = _cloth_over_ball_simulated(ball)
    dmin = 0.003
    g = part.vertex_ids
    # the simulation without a thickness leaves the cloth closer than d_min to the ball in frame 2
    assert start_distance(G[2], part.faces, bodies[2], body_faces, part.boundary) < 0.5 * dmin
    thick = PhysicsPrediction(V, F, labels, boundary, replace(mat, contact_offset=dmin), 25.0)
    thin = PhysicsPrediction(V, F, labels, boundary, mat, 25.0)(frames[1], frames[2], frames[2], frames[3])
    x = thick(frames[1], frames[2], frames[2], frames[3])
    assert x is not None and thick.last_stats.n_contacts > 0
    assert start_distance(x[g], part.faces, bodies[3], body_faces, part.boundary) > 0.95 * dmin
    # the thickness moves the cloth off the ball by about d_min, not more
    shift = np.linalg.norm(x[g] - thin[g], axis=1)
    assert 0.5 * dmin < shift.max() < 3 * dmin, shift.max()
