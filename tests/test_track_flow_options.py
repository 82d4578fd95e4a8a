"""The flow start's options for captures made elsewhere (issue 22 part 2), against synthetic truth.

- scaled_flow: the flow computed at half size recovers a known shift of several pixels;
- colour corrections: on a cloth whose texture differs only in hue (its luma is flat), the
  corrections on luma cannot see an 8 mm error and those on the colour-opponent channels remove it;
  the coarse-to-fine (half-size first) corrections do too;
- bend_reference="start": a fold the garment formed (the template is flat) and then moved
  rigidly is recovered from half the sheet's projections, where the bending toward the template's
  hinges pulls it open by centimetres; so does the corrections' "previous" reference (the
  hinges of a given mesh, the tracked frame t-1).
"""

from __future__ import annotations

import numpy as np
import pytest

from physavatar.stages.track.flow import (FlowObservation, FlowPrediction, ReferenceAppearance, image_channels,
                                          rasterize, scaled_flow, to_gray8, visible_vertices)
from test_flow import _fold, _grid, _motion, _rig, _texture


def test_scaled_flow_recovers_a_shift_of_several_pixels():
    H, W = 96, 128
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    shift = np.array([5.3, -3.6])
    a = to_gray8(_texture(x / 400, y / 400))
    b = to_gray8(_texture((x - shift[0]) / 400, (y - shift[1]) / 400))
    f = scaled_flow(a, b, "medium", 2)
    err = np.linalg.norm(f[16:-16, 16:-16].reshape(-1, 2) - shift, axis=1)
    assert np.median(err) < 0.25, np.median(err)


def _hue_render(V: np.ndarray, F: np.ndarray, rest: np.ndarray, cam) -> np.ndarray:
    """[H, W, 3] sRGB: a texture (fixed to the rest surface) that changes only the hue, at constant
    luma 0.299 R + 0.587 G + 0.114 B = 0.5, on a grey of the same luma."""
    luma = np.array([0.299, 0.587, 0.114])
    u = np.array([0.587, -0.299, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(luma, u)
    v /= np.linalg.norm(v)
    _, face, bary = rasterize(V, F, cam)
    img = np.full((cam.height, cam.width, 3), 0.5)
    hit = face >= 0
    P = np.einsum("nk,nkd->nd", bary[hit], rest[F[face[hit]]])
    p1 = 2 * _texture(P[:, 0], P[:, 2]) - 1
    p2 = 2 * _texture(P[:, 2] + 0.3, P[:, 0] - 0.2) - 1
    img[hit] = 0.5 + 0.3 * (p1[:, None] * u + p2[:, None] * v)
    return img


def test_colour_corrections_see_a_texture_that_only_the_hue_shows():
    V0, F = _grid(21, 0.4)
    cams = _rig()
    truth = V0 + _motion(V0)
    ref_views = [_hue_render(V0, F, V0, c) for c in cams]
    images = [_hue_render(truth, F, V0, c) for c in cams]
    g = to_gray8(images[0])
    assert g.max() - g.min() <= 1  # no pattern in luma at all
    pairs = image_channels(images[0], ref_views[0], "colour")
    assert len(pairs) == 3 and min(int(p[0].max()) - int(p[0].min()) for p in pairs[1:]) > 40
    start = V0 + np.array([0.0, 0.0, 0.008])
    e0 = np.linalg.norm(start - truth, axis=1).mean()
    fp = FlowPrediction(F, np.ones(len(V0), bool), F)
    err = {}
    for name, colour, kw in (("luma", False, {"iterations": 1}), ("colour", True, {"channels": "colour"}),
                             ("colour, coarse first", True, {"channels": "colour", "coarse": 1, "iterations": 1})):
        ref = ReferenceAppearance(V0, F, cams, ref_views, colour=colour)
        X = fp.correct(start, cams, images, ref, **{"iterations": 2, "prior_weight": 0.0, **kw})
        err[name] = np.linalg.norm(X - truth, axis=1).mean()
    assert e0 > 8e-3
    assert err["luma"] > 0.8 * e0, err  # blind: the luma is flat
    assert err["colour"] < 1e-3, err
    assert err["colour, coarse first"] < 1e-3, err


def test_bending_toward_the_start_keeps_a_fold_the_garment_formed():
    """The template is the flat sheet; the garment has since folded 60 degrees along its middle
    (an isometry: every edge keeps its length) and now moves rigidly. Only the left half and the
    crease are seen. Bending toward the template's hinges pulls the unseen half back toward flat;
    toward the start's (the previous frame's shape) it follows the seen half rigidly, to the
    second-order hold of the flat hinges (about 1 mm at the far edge, against 0.2 m)."""
    V0, F = _grid(9, 0.4)
    start = _fold(V0, 60.0)
    a = np.radians(6.0)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    truth = start @ R.T + [0.008, -0.005, 0.004]
    left = np.flatnonzero(V0[:, 0] < 1e-9)
    obs = []
    for cam in _rig():
        idx = np.intersect1d(np.flatnonzero(visible_vertices(truth, F, cam)), left)
        obs.append(FlowObservation(cam, idx, cam.project(truth[idx])[0]))
    solve = np.ones(len(V0), bool)
    kw = {"smoothness": 0.0, "iterations": 15, "rest": V0, "iso_weight": 10.0, "bend_weight": 10.0}
    to_rest = FlowPrediction(F, solve, F, **kw).lift(start, obs)
    to_start = FlowPrediction(F, solve, F, bend_reference="start", **kw).lift(start, obs)
    e_rest = np.linalg.norm(to_rest - truth, axis=1).max()
    e_start = np.linalg.norm(to_start - truth, axis=1).max()
    assert e_rest > 0.1, e_rest
    assert e_start < 2e-3, e_start
    # the corrections' "previous" reference: the hinges of a given mesh (here the folded start, as
    # the tracked frame t-1 would be) held in place of the template's
    fp = FlowPrediction(F, solve, F, **kw)
    to_previous = fp.lift(start, obs, bend_rest=fp.hinge_lengths(start))
    assert np.linalg.norm(to_previous - truth, axis=1).max() < 2e-3
    with pytest.raises(ValueError, match="previous"):
        fp.correct(start, [], [], None, bend_reference="previous")



def _observe(truth, F, where):
    """Exact flow observations of the vertices ``where`` that each camera of the rig sees."""
    obs = []
    for cam in _rig():
        idx = np.intersect1d(np.flatnonzero(visible_vertices(truth, F, cam)), where)
        obs.append(FlowObservation(cam, idx, cam.project(truth[idx])[0]))
    return obs


def _lifts(start, obs, F, solve, kw, refs):
    """The lift from ``start`` under each bending reference of ``refs``."""
    return {ref: FlowPrediction(F, solve, F, bend_reference=ref, **kw).lift(start, obs) for ref in refs}


def test_bending_toward_moved_hinges_keeps_a_fold_and_flattens_noise():
    """bend_reference="moved" (per hinge): a hinge the start has moved more than ``bend_moved``
    from the template's holds the start's distance, the others the template's. On the folded
    sheet above it keeps the fold as "start" does (the crease's hinges moved by centimetres); on
    a flat sheet with sub-millimetre noise (no hinge moved 2 mm) it is exactly "rest", which pulls
    the unseen half flat where "start" keeps the noise."""
    V0, F = _grid(9, 0.4)
    solve = np.ones(len(V0), bool)
    kw = {"smoothness": 0.0, "iterations": 15, "rest": V0, "iso_weight": 10.0, "bend_weight": 10.0}
    left = np.flatnonzero(V0[:, 0] < 1e-9)

    def seen(truth):
        return _observe(truth, F, left)

    def lifts(start, obs):
        return _lifts(start, obs, F, solve, kw, ("rest", "start", "moved"))

    start = _fold(V0, 60.0)
    truth = start + [0.008, -0.005, 0.004]
    out = lifts(start, seen(truth))
    err = {ref: np.linalg.norm(X - truth, axis=1).max() for ref, X in out.items()}
    assert err["rest"] > 0.1 and err["start"] < 2e-3 and err["moved"] < 2e-3, err

    noisy = V0 + np.random.default_rng(0).normal(0.0, 5e-4, V0.shape) * [0.0, 0.0, 1.0]
    truth = V0 + [0.008, -0.005, 0.004]
    out = lifts(noisy, seen(truth))
    assert np.array_equal(out["moved"], out["rest"])
    right = V0[:, 0] > 1e-9  # the unseen half
    bump = {ref: np.abs(X[right, 2] - truth[right, 2]).mean() for ref, X in out.items()}
    assert bump["start"] > 1.5 * bump["rest"], bump
    with pytest.raises(ValueError, match="moved"):
        FlowPrediction(F, solve, F, bend_reference="bent", **kw)

def test_patterned_opponents_tells_a_hue_pattern_from_a_plain_colour_with_noise():
    """The hue-only texture shows a pattern in the opponent channels; a plain red cloth rendered
    with per-pixel noise (as a path tracer's) shows none, though its noise is as strong."""
    from physavatar.stages.track.flow import patterned_opponents

    V0, F = _grid(21, 0.4)
    cams = _rig()
    solve = np.ones(len(V0), bool)
    assert patterned_opponents(V0, F, solve, cams, [_hue_render(V0, F, V0, c) for c in cams]) == (True, True)
    rng = np.random.default_rng(0)
    plain = []
    for c in cams:
        img = np.full((c.height, c.width, 3), 0.5)
        hit = rasterize(V0, F, c)[1] >= 0
        img[hit] = [0.7, 0.2, 0.25]
        plain.append(np.clip(img + rng.normal(0, 0.03, img.shape), 0, 1))
    assert patterned_opponents(V0, F, solve, cams, plain) == (False, False)


def test_bending_toward_seen_hinges_keeps_a_seen_fold_and_undoes_an_unseen_one():
    """bend_reference="seen" (session 24): the start's hinge distance only where the lift's flow
    sees both vertices opposite the hinge in ``bend_views`` cameras and it moved more than
    ``bend_moved``; the template's elsewhere. A fold every camera sees is kept as "moved" keeps it;
    a fold the start has made where no camera sees (a drifted hem) is opened back to the true flat
    sheet, where "moved" keeps it because it moved, and holds the unseen half 0.1 m off."""
    V0, F = _grid(9, 0.4)
    solve = np.ones(len(V0), bool)
    kw = {"smoothness": 0.0, "iterations": 15, "rest": V0, "iso_weight": 10.0, "bend_weight": 10.0}

    def observe(truth, where):
        return _observe(truth, F, where)

    def lifts(start, obs):
        return _lifts(start, obs, F, solve, kw, ("rest", "moved", "seen"))

    shift = np.array([0.008, -0.005, 0.004])
    start = _fold(V0, 60.0)  # a real fold, seen by the cameras on both sides of the crease
    truth = start + shift
    out = lifts(start, observe(truth, np.arange(len(V0))))
    err = {ref: np.linalg.norm(X - truth, axis=1).max() for ref, X in out.items()}
    assert err["seen"] < 2e-3 and err["moved"] < 2e-3 and err["rest"] > 2 * err["seen"], err

    truth = V0 + shift  # the sheet is flat; the start folded its unseen half
    out = lifts(start, observe(truth, np.flatnonzero(V0[:, 0] < -1e-9)))
    right = V0[:, 0] > 1e-9
    err = {ref: np.linalg.norm(X[right] - truth[right], axis=1).mean() for ref, X in out.items()}
    assert err["moved"] > 0.05 and err["seen"] < 0.2 * err["moved"] and err["seen"] < 2 * err["rest"] + 1e-3, err


def test_fit_blend_keeps_the_flow_start_of_the_free_garment_and_the_fit_of_the_body():
    """flow.fit_blend (session 24): the final corrections of frame t start from the fit for the
    skinned vertices (the body) and, for the free garment, from its flow start plus ``fit_blend``
    of the fit's move; 1 (default) is the fit as before."""
    from dataclasses import replace

    from physavatar.stages.track import TrackConfig
    from physavatar.stages.track.prediction import FrameStarts

    class Lift:  # the final corrections, recorded rather than run
        def refine(self, vertices, views, masks):
            self.got = np.array(vertices)
            return vertices

    rng = np.random.default_rng(1)
    start, fit = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    skinned = np.array([True, True, False, False, False, True])
    for blend in (1.0, 0.5, 0.0):
        s = object.__new__(FrameStarts)
        cfg = TrackConfig()
        s.cfg = replace(cfg, flow=replace(cfg.flow, fit_blend=blend))
        s.flow, s.skinned, s.frames, s._grey, s._masks = Lift(), skinned, [0, 1], {1: []}, {}
        s.flow_cfg = s.cfg.flow
        s.refine(1, fit.astype(np.float32), start.astype(np.float32))
        want = np.where(skinned[:, None], fit, start + blend * (fit - start))
        assert np.allclose(s.flow.got, want, atol=1e-6), blend
    # the plain-garment rule keeps the fit whole: a plain garment's flow follows the shading
    s.cfg = replace(cfg, flow=replace(cfg.flow, fit_blend=0.0, plain="plain"))
    s.flow_cfg = s._flow_settings(None, [])
    s.refine(1, fit.astype(np.float32), start.astype(np.float32))
    assert s.flow_cfg.fit_blend == 1.0 and np.allclose(s.flow.got, fit, atol=1e-6)


def test_bending_toward_the_physics_step_keeps_its_fold_where_no_camera_sees():
    """bend_reference="physics" (session 37): the bending terms hold the hinges of the frame's
    physics step (the lift's reference, ``carried``) instead of the template's. The template is the
    flat sheet; the step has folded it 60 degrees (an isometry) and moved it, and no camera sees
    it. Every term of the lift is then zero at the step, so the start (prediction and corrections)
    is the step itself; toward the template's hinges the unseen half is pulled back toward flat
    (6.6 mm at the far edge in two lifts, against the membrane that holds it to the step)."""
    from physavatar.stages.track.flow import FlowStart

    V0, F = _grid(9, 0.4)
    step = _fold(V0, 60.0) + [0.008, -0.005, 0.004]
    solve = np.ones(len(V0), bool)
    kw = {"smoothness": 3.0, "iterations": 5, "rest": V0, "iso_weight": 3.0, "bend_weight": 10.0}
    out = {}
    for ref in ("rest", "physics"):
        fs = FlowStart(FlowPrediction(F, solve, F, bend_reference=ref, **kw), [], V0, [], corrections=0)
        X = fs(V0, [], [], step, carried=step)
        # the frame's corrections (no camera: the regularisers and the pull toward the estimate)
        out[ref] = fs.flow.correct(X, [], [], None, iterations=2, bend_weight=5.0, physics=fs._carried)
    err = {ref: np.linalg.norm(X - step, axis=1).max() for ref, X in out.items()}
    assert err["physics"] < 1e-9 and err["rest"] > 3e-3, err
    fp = FlowPrediction(F, solve, F, bend_reference="physics", **kw)
    assert np.allclose(fp.hinge_lengths(out["physics"]), fp.hinge_lengths(step), atol=1e-12)
    # without a step (frame 2, or none intersection-free) "physics" is the template's reference
    no_step = FlowStart(fp, [], V0, [], corrections=0)(V0, [], [], step)
    to_rest = FlowStart(FlowPrediction(F, solve, F, **kw), [], V0, [], corrections=0)(V0, [], [], step)
    assert np.array_equal(no_step, to_rest)
