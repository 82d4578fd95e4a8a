"""The flow of the texture, not of the shading (issue 22 part 2, session 18): ``flow.highpass``,
``flow.texture_blur`` and ``flow.carry="near"``, against analytic and synthetic truth.

- a plain sheet whose shading moved (the light moved, not the sheet): the corrections on the raw
  views follow the shading by millimetres, on the high-passed views they keep it in place; a
  textured sheet with a real error is still corrected;
- the gate's texture measured on the blurred view: a sinusoid pattern keeps the closed-form
  fraction exp(-2 pi^2 sigma^2 / P^2) of its strength, a one-pixel checker (aliased speckle) none;
- the "near" carry's weights are exp(-(d / range)^2) of each vertex's distance from the body.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from test_flow import _grid, _motion, _render, _rig
from test_track_texture_gate import _shaded

from physavatar.stages.track.channels import shading_free, texture_strength
from physavatar.stages.track.flow import FlowPrediction, ReferenceAppearance, _blurred


def test_shading_free_removes_a_linear_shading_exactly():
    """A Gaussian blur keeps a linear ramp, so the high-pass of texture + ramp is that of the
    texture alone (up to uint8 rounding), away from the border."""
    rng = np.random.default_rng(0)
    tex = rng.integers(60, 120, (64, 64)).astype(np.float64)
    y, x = np.mgrid[0:64, 0:64].astype(np.float64)
    ramp = 1.5 * x + 0.7 * y
    a = shading_free(np.rint(tex).astype(np.uint8), 2.0).astype(int)
    b = shading_free(np.clip(np.rint(tex + ramp), 0, 255).astype(np.uint8), 2.0).astype(int)
    inner = (slice(8, -8), slice(8, -8))
    assert np.abs(a - b)[inner].max() <= 1
    assert np.abs(shading_free(np.clip(np.rint(40 + ramp), 0, 255).astype(np.uint8), 2.0)[inner].astype(int) - 128).max() <= 1


def test_highpass_keeps_a_plain_sheet_where_its_shading_moved():
    V0, F = _grid(21, 0.4)
    cams = _rig()
    ref = ReferenceAppearance(V0, F, cams, [_shaded(V0, F, c, np.array([-0.05, 0.0, 0.0])) for c in cams])
    images = [_shaded(V0, F, c, np.array([0.05, 0.0, 0.03])) for c in cams]  # the light moved, not the sheet
    solve = np.ones(len(V0), bool)
    err = {}
    for key, kw in (("raw", {}), ("highpass", {"highpass": 2.0}),
                    ("gated", {"highpass": 2.0, "min_texture": 0.8, "texture_blur": 1.0}),
                    ("gated raw", {"min_texture": 3.0})):
        fp = FlowPrediction(F, solve, F, rest=V0, iso_weight=10.0, **kw)
        X = fp.correct(V0, cams, images, ref, iterations=2, prior_weight=0.01, smoothness=0.1)
        err[key] = np.linalg.norm(X - V0, axis=1).mean()
    assert err["raw"] > 2e-3, err  # followed the shading
    assert err["highpass"] < 0.2 * err["raw"], err  # the shading's slow part is gone, its edge is not
    assert err["gated"] < 0.3e-3, err  # and the gate drops what is left on a view without texture
    assert err["gated raw"] < 0.3e-3, err  # the gate alone, on the raw views (session 16's flow.min_texture)
    # a textured sheet with a real error is still corrected on the high-passed, gated views
    truth = V0 + _motion(V0)
    tex_ref = ReferenceAppearance(V0, F, cams, [_render(V0, F, V0, c) for c in cams])
    tex_images = [_render(truth, F, V0, c) for c in cams]
    e0 = np.linalg.norm(V0 - truth, axis=1).mean()
    for kw in ({"highpass": 2.0, "min_texture": 0.8, "texture_blur": 1.0}, {"min_texture": 3.0}):
        fp = FlowPrediction(F, solve, F, rest=V0, iso_weight=10.0, **kw)
        X = fp.correct(V0, cams, tex_images, tex_ref, iterations=2, prior_weight=0.01, smoothness=0.1)
        assert np.linalg.norm(X - truth, axis=1).mean() < 0.2 * e0, kw


def test_texture_on_the_blurred_view():
    """I = 128 + A sin(wx) + A sin(wy), period P = 5 px: its strength A sin(w) / sqrt 2
    (test_track_texture_gate) times the Gaussian's response exp(-2 pi^2 sigma^2 / P^2) at
    sigma = 1 px; pixel-scale speckle (independent per pixel, a plain fabric's weave aliased) keeps
    a small part of it."""
    A, P, sigma = 20.0, 5.0, 1.0
    w = 2 * np.pi / P
    y, x = np.mgrid[0:60, 0:60].astype(np.float64)
    img = np.rint(128 + A * np.sin(w * x) + A * np.sin(w * y)).astype(np.uint8)
    inner = (slice(8, -8), slice(8, -8))
    got = np.median(texture_strength(_blurred(img, sigma))[inner])
    expect = A * np.sin(w) / np.sqrt(2) * np.exp(-2 * np.pi ** 2 * sigma ** 2 / P ** 2)
    assert abs(got - expect) < 0.05 * expect, (got, expect)
    speckle = np.random.default_rng(1).integers(88, 168, (60, 60)).astype(np.uint8)
    raw = np.median(texture_strength(speckle)[inner])
    assert raw > 5.0  # strong texture in both directions, as the raw view sees it
    kept = np.median(texture_strength(_blurred(speckle, sigma))[inner]) / raw
    assert kept < 0.35 < np.exp(-2 * np.pi ** 2 * sigma ** 2 / P ** 2), kept  # less than the pattern keeps


def test_near_carry_weights_fall_with_the_distance_from_the_body():
    """Body: a large square in z = 0; garment vertices above its middle at known heights."""
    from physavatar.stages.track.config import FlowConfig, TrackConfig
    from physavatar.stages.track.prediction import FrameStarts

    body_v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    h = np.array([0.005, 0.01, 0.02, 0.04, 0.2])
    garment_v = np.stack([np.zeros_like(h), np.linspace(-0.1, 0.1, len(h)), h], 1)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [6, 7, 8]])
    template = SimpleNamespace(vertices=np.vstack([body_v, garment_v]), faces=faces,
                               garment_mask=np.r_[np.zeros(4, bool), np.ones(len(h), bool)])
    fs = FrameStarts.__new__(FrameStarts)
    fs.template, fs.cfg, fs._carry_w = template, TrackConfig(flow=FlowConfig(carry="near", carry_range=0.02)), None
    w = fs.carry_weights()
    np.testing.assert_allclose(w[4:], np.exp(-np.square(np.minimum(h, 0.08) / 0.02)), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(w[:4], 1.0)  # the body itself moves with the body


def test_plain_rule_tells_a_plain_sheet_from_a_textured_one():
    """``flow.plain="auto"``: a plain sheet under a soft light with pixel noise (a render's, or a
    fabric's aliased weave) measures below ``plain_texture`` on the views blurred by 1 px, the
    procedurally textured sheet above; a plain garment's flow settings get the gate (and, from "still", the near
    carry), a patterned one's stay as configured."""
    from physavatar.stages.track.channels import garment_texture
    from physavatar.stages.track.config import FlowConfig, TrackConfig
    from physavatar.stages.track.prediction import PLAIN_BLUR, FrameStarts

    V0, F = _grid(21, 0.4)
    cams = _rig()
    rng = np.random.default_rng(0)
    region = np.ones(len(V0), bool)
    plain = [np.clip(_shaded(V0, F, c, np.array([0.0, 0.0, 0.0])) + rng.normal(0, 0.02, (c.height, c.width, 1)), 0, 1)
             for c in cams]
    textured = [_render(V0, F, V0, c) for c in cams]
    limit = FlowConfig().plain_texture
    t_plain = garment_texture(V0, F, region, cams, plain, PLAIN_BLUR)
    t_tex = garment_texture(V0, F, region, cams, textured, PLAIN_BLUR)
    assert t_plain < limit < t_tex, (t_plain, t_tex)
    assert texture_strength(np.rint(plain[0][..., 0] * 255).astype(np.uint8)).mean() > limit  # raw, the noise passes

    fs = FrameStarts.__new__(FrameStarts)
    fs.template = SimpleNamespace(faces=F)
    fs.skinned, fs.train, fs.cfg = ~region, cams, TrackConfig()
    got = fs._flow_settings(V0, plain)  # the default carry (physics, session 26) is kept
    assert fs.plain and (got.min_texture, got.texture_blur, got.carry) == (limit, PLAIN_BLUR, "physics")
    fs.cfg = TrackConfig(flow=FlowConfig(carry="still"))  # "still" becomes the near carry
    assert fs._flow_settings(V0, plain).carry == "near" and fs.plain
    fs.cfg = TrackConfig()
    assert fs._flow_settings(V0, textured) == fs.cfg.flow and not fs.plain
    fs.cfg = TrackConfig(flow=FlowConfig(plain="patterned"))
    assert fs._flow_settings(V0, plain) == fs.cfg.flow and fs.garment_texture is None
