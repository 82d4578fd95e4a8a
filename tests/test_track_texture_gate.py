"""Flow observations only where the view has texture (issue 22 part 2, ``flow.min_texture``), and
the prediction's lift relative to the body's motion (``flow.carry="body"``), against analytic and
synthetic truth.

- texture_strength: the structure tensor's smaller eigenvalue of a sum of two sinusoids (known in
  closed form through the Sobel filter's response) and zero for stripes;
- a plain sheet that has not moved, whose shading has (the light moved): the corrections on all
  pixels follow the shading and move it by millimetres, those gated by texture keep it in place;
  a textured sheet is still corrected with the gate on.
"""

from __future__ import annotations

import numpy as np

from physavatar.stages.track.channels import texture_strength
from physavatar.stages.track.flow import FlowPrediction, ReferenceAppearance, rasterize
from test_flow import _grid, _motion, _render, _rig


def test_texture_strength_of_sinusoids_and_stripes():
    """I = 128 + A sin(wx) + A sin(wy), period 5 px = the window: the Sobel x derivative / 8 is
    A sin(w) cos(wx) (the central difference; the [1 2 1] smoothing acts along y, where that term
    is constant), and over a full period in a 5 x 5 window the tensor is diagonal with both
    entries half its square: sqrt(lambda_min) = A sin(w) / sqrt 2.
    Stripes (one sinusoid) have no second direction: zero."""
    A, w = 20.0, 2 * np.pi / 5
    y, x = np.mgrid[0:60, 0:60].astype(np.float64)
    both = texture_strength(np.rint(128 + A * np.sin(w * x) + A * np.sin(w * y)).astype(np.uint8))
    stripes = texture_strength(np.rint(128 + A * np.sin(w * x)).astype(np.uint8))
    expect = A * np.sin(w) / np.sqrt(2)
    inner = (slice(5, -5), slice(5, -5))
    assert abs(np.median(both[inner]) - expect) < 0.02 * expect, (np.median(both[inner]), expect)
    assert np.median(stripes[inner]) < 0.05 * expect


def _shaded(V: np.ndarray, F: np.ndarray, cam, light: np.ndarray) -> np.ndarray:
    """[H, W, 3] a plain sheet lit by a soft spot centred at ``light`` (a point in the sheet's
    plane): the shading is a function of the world position, not of the cloth."""
    _, face, bary = rasterize(V, F, cam)
    img = np.full((cam.height, cam.width), 0.5)
    hit = face >= 0
    P = np.einsum("nk,nkd->nd", bary[hit], V[F[face[hit]]])
    img[hit] = 0.35 + 0.4 * np.exp(-np.sum((P - light) ** 2, 1) / (2 * 0.1 ** 2))
    return np.repeat(img[..., None], 3, 2)


def test_the_texture_gate_keeps_a_plain_sheet_where_its_shading_moved():
    V0, F = _grid(21, 0.4)
    cams = _rig()
    ref = ReferenceAppearance(V0, F, cams, [_shaded(V0, F, c, np.array([-0.05, 0.0, 0.0])) for c in cams])
    images = [_shaded(V0, F, c, np.array([0.05, 0.0, 0.03])) for c in cams]  # the light moved, not the sheet
    solve = np.ones(len(V0), bool)
    err = {}
    for gate in (0.0, 3.0):
        fp = FlowPrediction(F, solve, F, rest=V0, iso_weight=10.0, min_texture=gate)
        X = fp.correct(V0, cams, images, ref, iterations=2, prior_weight=0.01, smoothness=0.1)
        err[gate] = np.linalg.norm(X - V0, axis=1).mean()
    assert err[0.0] > 2e-3, err  # followed the shading
    assert err[3.0] < 0.3e-3, err
    # a textured sheet with a real error is still corrected with the gate on
    truth = V0 + _motion(V0)
    tex_ref = ReferenceAppearance(V0, F, cams, [_render(V0, F, V0, c) for c in cams])
    tex_images = [_render(truth, F, V0, c) for c in cams]
    fp = FlowPrediction(F, solve, F, rest=V0, iso_weight=10.0, min_texture=3.0)
    X = fp.correct(V0, cams, tex_images, tex_ref, iterations=2, prior_weight=0.01, smoothness=0.1)
    e0 = np.linalg.norm(V0 - truth, axis=1).mean()
    assert np.linalg.norm(X - truth, axis=1).mean() < 0.2 * e0
