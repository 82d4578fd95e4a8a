"""Flow observations only where the view has texture (issue 22 part 2, ``flow.min_texture``), and
the prediction's lift relative to the body's motion (``flow.carry="body"``), against analytic and
synthetic truth.

- texture_strength: the structure tensor's smaller eigenvalue of a sum of two sinusoids (known in
  closed form through the Sobel filter's response) and zero for stripes;
- the gate on a plain sheet whose shading moved is checked in test_track_shading.py, beside the
  high-pass and the blurred-view gate.
"""

from __future__ import annotations

import numpy as np
from test_flow import _grid, _rig

from physavatar.stages.track.channels import texture_strength
from physavatar.stages.track.flow import FlowPrediction, rasterize


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


def test_carry_body_moves_what_no_flow_observes_with_the_body():
    """The sheet hangs from its top row (placed by skinning) and turns 10 degrees with the body
    about a vertical axis 0.1 m behind it (the free vertices move 27 mm on average). No flow
    observes them (views without texture, gated out). Relative to frame t-1 where it was
    (``carry="still"``) the membrane, edge-length and bending terms drag them along with the top
    row only partly; relative to frame t-1 carried by the body's motion (``carried``, here the
    truth) they are where the body took them."""
    from physavatar.stages.track.flow import FlowStart

    V0, F = _grid(9, 0.4)
    top = V0[:, 2] > V0[:, 2].max() - 1e-9
    a = np.radians(10.0)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    axis = np.array([0.0, 0.1, 0.0])
    truth = (V0 - axis) @ R.T + axis
    start = V0.copy()
    start[top] = truth[top]
    cams = _rig()
    blank = [np.zeros((c.height, c.width, 3)) for c in cams]
    fp = FlowPrediction(F, ~top, F, smoothness=3.0, rest=V0, iso_weight=3.0, bend_weight=10.0, min_texture=3.0)
    fs = FlowStart(fp, cams, V0, blank, corrections=0)
    still = fs(V0, blank, blank, start)
    body = fs(V0, blank, blank, start, carried=truth)
    e_still = np.linalg.norm(still - truth, axis=1)[~top].mean()
    e_body = np.linalg.norm(body - truth, axis=1)[~top].mean()
    assert e_still > 0.01, e_still
    assert e_body < 1e-4, e_body


def test_bad_carry_is_one_clear_error():
    import pytest

    from physavatar.errors import PhysavatarError
    from physavatar.stages.track import TrackConfig
    from physavatar.stages.track.config import FlowConfig
    from physavatar.stages.track.stage import _check_config


    cfg = TrackConfig(flow=FlowConfig(carry="skin"))
    with pytest.raises(PhysavatarError, match="flow.carry"):
        _check_config(cfg, _fake_capture())


def _fake_capture():
    from pathlib import Path
    from types import SimpleNamespace

    from physavatar.camera import Camera, intrinsics, look_at

    cams = [Camera(f"c{i}", 64, 64, intrinsics(64, 64, 40.0), look_at([0, -2, 0], [0, 0, 0])) for i in range(2)]
    return SimpleNamespace(cameras=cams, frames=[0, 1], root=Path("."))
