"""Lights by name and as JSON (physavatar.render.lights): `physavatar render --light X` and
`physavatar relight --light X` build the same scene for every name, each through its own command."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from physavatar.capture import load_capture
from physavatar.cli import app
from physavatar.files import load_npz, save_npz_atomic
from physavatar.render import Ambient, EnvMap, mitsuba
from physavatar.render.lights import LIGHT_NAMES, light_to_json, load_lights, named_lights, save_lights

runner = CliRunner()


class _Built(Exception):
    """Raised by the recording scene_dict: the command has built its first scene."""


@pytest.fixture(scope="module")
def scene_of(tmp_path_factory, tiny_capture):
    """A fit-appearance folder, an avatar built from it and a sequence whose first frame is the
    capture's frame 2; returns ``build(argv) -> (SceneSpec, scene dict)`` of the first scene the
    command builds."""
    from physavatar.stages.avatar import build_avatar
    from physavatar.data.animated import AnimatedSequence as Sequence

    root = tmp_path_factory.mktemp("lights")
    cap = load_capture(tiny_capture)
    t = cap.template
    fit = root / "fit"
    fit.mkdir()
    np.save(fit / "texture_linear.npy", np.load(cap.ground_truth / "texture_linear.npy").astype(np.float32))
    face_uvs = t.face_uvs.astype(np.float32)
    save_npz_atomic(fit / "atlas.npz", face_uvs=face_uvs)
    lights = load_lights(cap.ground_truth / "lighting.json")
    save_lights(fit / "light.json", [Ambient((0.3, 0.32, 0.35))] + lights[1:], {"model": "studio"})
    av = build_avatar(cap.root, root / "avatar", material="denim", texture_dir=fit)
    V = load_npz(cap.ground_truth / "meshes.npz")["vertices"][2:4]
    Sequence(V, t.faces, t.labels, face_uvs, cap.fps, av.root).save(root / "seq", {}, ply=False)
    hdr = root / "grey.hdr"
    mitsuba().Bitmap(np.full((8, 16, 3), 0.5, np.float32)).write(str(hdr))

    def build(argv, monkeypatch):
        import physavatar.render.scene as scene_mod

        made = []
        original = scene_mod.scene_dict

        def recording(spec, **kw):
            made.append((spec, original(spec, **kw)))
            raise _Built

        monkeypatch.setattr(scene_mod, "scene_dict", recording)
        r = runner.invoke(app, [str(a) for a in argv])
        monkeypatch.setattr(scene_mod, "scene_dict", original)
        assert isinstance(r.exception, _Built), r.output
        return made[0]

    return {"root": root, "capture": cap.root, "frame": cap.frames[2], "hdr": hdr, "build": build}


def _plain(x):
    """A scene dict's values as comparable numpy / Python data."""
    mi = mitsuba()
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, mi.ScalarTransform4f):
        return np.array(x.matrix, np.float64)
    if isinstance(x, mi.Bitmap):
        return np.array(x, np.float32)
    return x


def _same(a, b, where="") -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), (where, a.keys(), getattr(b, "keys", lambda: b)())
        for k in a:
            _same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b), where
    else:
        assert a == b, (where, a, b)


@pytest.mark.parametrize("name", [*LIGHT_NAMES, "hdr"])
def test_render_and_relight_build_the_same_scene(scene_of, monkeypatch, name):
    root = scene_of["root"]
    light = str(scene_of["hdr"]) if name == "hdr" else name
    spec_r, dict_r = scene_of["build"](["render", root / "seq", "--out", root / f"r_{name}", "--light", light,
                                        "--spp", "1", "--size", "16"], monkeypatch)
    spec_l, dict_l = scene_of["build"](["relight", scene_of["capture"], "--texture", root / "fit", "--light", light,
                                        "--frame", scene_of["frame"], "--out", root / f"l_{name}.png", "--spp", "1"],
                                       monkeypatch)
    # the lights: the same emitters, names and Mitsuba dicts
    names = [l.name for l in spec_r.lights]
    assert names == [l.name for l in spec_l.lights] and names
    for n in names:
        _same(_plain(dict_r[n]), _plain(dict_l[n]), n)
    _same(dict_r["integrator"], dict_l["integrator"], "integrator")
    # the meshes: one builder, the same frame, texture and atlas
    assert [m.name for m in spec_r.meshes] == [m.name for m in spec_l.meshes] == ["body", "garment"]
    for a, b in zip(spec_r.meshes, spec_l.meshes):
        assert a.twosided == b.twosided and a.material == b.material == "texture"
        for field in ("vertices", "faces", "uvs", "texture"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), (a.name, field)
    if name == "fitted":
        assert spec_r.lights[0].radiance == (0.3, 0.32, 0.35)


def test_named_lights_errors(tmp_path):
    from physavatar.errors import PhysavatarError

    with pytest.raises(PhysavatarError, match="disco"):
        named_lights("disco", (0, 0, 1))
    with pytest.raises(PhysavatarError, match="light.json"):
        named_lights("fitted", (0, 0, 1), fitted=tmp_path / "light.json")
    with pytest.raises(PhysavatarError, match="not found"):
        named_lights(str(tmp_path / "missing.exr"), (0, 0, 1))


def test_light_json_roundtrip(tmp_path):
    lights = named_lights("studio", (0.0, 0.0, 0.9)) + named_lights("point", (0.0, 0.0, 0.9))[:2] \
        + [named_lights("sun", (0, 0, 1))[1], EnvMap(str(tmp_path / "sky.hdr"), scale=0.5, rotation_deg=30.0)]
    save_lights(tmp_path / "light.json", lights, {"note": "test"})
    assert load_lights(tmp_path / "light.json") == lights
    with pytest.raises(ValueError, match="array"):
        light_to_json(named_lights("sky", (0, 0, 1))[0])
