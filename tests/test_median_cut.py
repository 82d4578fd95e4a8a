"""An environment map as lights (physavatar.render.median_cut), checked against closed forms: the
irradiance of a map that is linear in the direction, the map's total power, where a single bright
texel lies; and the viewer drawing a fitted environment (inline or an .exr file) with them."""

from __future__ import annotations

import numpy as np
import pytest

from physavatar.render.lights import Ambient, SunLight, envmap_directions
from physavatar.render.median_cut import median_cut_lights

S = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])


def _irradiance(lights, normals):
    E = np.zeros((len(normals), 3))
    for L in lights:
        if isinstance(L, Ambient):
            E += np.pi * np.asarray(L.radiance)
        else:
            E += np.maximum(normals @ np.asarray(L.to_sun), 0)[:, None] * np.asarray(L.irradiance)
    return E


def _normals(n=300):
    v = np.random.default_rng(0).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_linear_map_irradiance_and_power_match_the_closed_form():
    """L(ω) = (1 + ω·s)·(1, 0.5, 0.25): E(n) = π + (2π/3) n·s per unit colour, total power 4π; the
    map is turned 40° about +z, so s is where it lands in the world."""
    rot = np.radians(40.0)
    rz = np.array([[np.cos(rot), -np.sin(rot), 0], [np.sin(rot), np.cos(rot), 0], [0, 0, 1]])
    d = envmap_directions(64, 128)  # the map's own directions (rotation 0)
    img = (1.0 + d @ (rz.T @ S))[..., None] * np.array([1.0, 0.5, 0.25])
    N = _normals()
    exact = (np.pi + 2 * np.pi / 3 * (N @ S))[:, None] * np.array([1.0, 0.5, 0.25])
    errs = []
    for n in (4, 16, 64):
        lights = median_cut_lights(img, n, rotation_deg=40.0)
        assert sum(isinstance(L, SunLight) for L in lights) <= n
        power = sum(np.asarray(L.irradiance) for L in lights if isinstance(L, SunLight)) + 4 * np.pi * np.asarray(
            next(L.radiance for L in lights if isinstance(L, Ambient)))
        np.testing.assert_allclose(power, 4 * np.pi * np.array([1.0, 0.5, 0.25]), rtol=2e-3)  # texel quadrature
        errs.append(np.abs(_irradiance(lights, N) - exact).max() / exact.max())
    assert errs[1] < 0.06 and errs[2] < 0.02 and errs[2] < errs[1] < errs[0], errs


def test_constant_map_is_ambient_and_a_bright_texel_one_light():
    const = median_cut_lights(np.full((8, 16, 3), 0.7), 8, scale=2.0)
    assert len(const) == 1 and isinstance(const[0], Ambient) and np.allclose(const[0].radiance, 1.4)
    img = np.zeros((32, 64, 3))
    img[16, 32] = 5.0  # just below the horizon, the centre column: +x (docs of render.lights)
    for rot, axis in ((0.0, [1, 0, 0]), (90.0, [0, 1, 0])):
        (sun,) = median_cut_lights(img, 8, rotation_deg=rot)
        assert np.degrees(np.arccos(np.dot(sun.to_sun, axis))) < 6.0, (rot, sun.to_sun)


def test_bad_maps_are_refused():
    with pytest.raises(ValueError, match="finite"):
        median_cut_lights(np.full((4, 8, 3), np.nan))
    with pytest.raises(ValueError, match="n_lights"):
        median_cut_lights(np.ones((4, 8, 3)), 0)


def test_viewer_draws_a_fitted_environment(tmp_path):
    pytest.importorskip("viser")
    from physavatar.render import EnvMap, mitsuba
    from physavatar.render.lights import light_to_json, sky_envmap
    from physavatar.viewer.scene import ENV_LIGHTS, _viser_lights

    V = np.random.default_rng(1).random((50, 3))
    img = sky_envmap(16, 32)
    notes: list[str] = []
    inline = _viser_lights({"lights": [light_to_json(EnvMap(img, rotation_deg=15.0))]}, V, notes)
    kinds = [L["kind"] for L in inline]
    assert kinds.count("ambient") == 1 and 1 <= kinds.count("directional") <= ENV_LIGHTS
    assert "median cut" in notes[-1]
    mitsuba().Bitmap(img).write(str(tmp_path / "sky.exr"))
    from_file = _viser_lights({"lights": [{"type": "EnvMap", "image": "sky.exr", "rotation_deg": 15.0}]}, V, notes,
                              tmp_path)
    assert len(from_file) == len(inline)  # the same map (rounded to 6 digits inline): the same power
    assert sum(L["intensity"] for L in from_file) == pytest.approx(sum(L["intensity"] for L in inline), rel=1e-3)
    # three.js's units: a directional light's intensity is the irradiance, an ambient one's is π × radiance
    amb = _viser_lights({"lights": [{"type": "Ambient", "radiance": [0.2, 0.2, 0.2]}]}, V, notes)[0]
    assert amb["intensity"] == pytest.approx(0.2 * np.pi)
    sun = _viser_lights({"lights": [{"type": "SunLight", "to_sun": [0, 0, 2], "irradiance": 3.0}]}, V, notes)[0]
    assert sun["intensity"] == pytest.approx(3.0) and np.allclose(np.asarray(sun["position"]) / np.linalg.norm(
        sun["position"]), [0, 0, 1])
    missing = _viser_lights({"lights": [{"type": "EnvMap", "image": "nope.exr"}]}, V, notes, tmp_path)
    assert missing == [] and "not drawn" in notes[-1]
