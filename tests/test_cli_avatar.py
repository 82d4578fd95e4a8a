"""The avatar commands end to end on the tiny capture: build-avatar, animate, render, export."""

import numpy as np
import pytest
from typer.testing import CliRunner

from physavatar.cli import app

runner = CliRunner()


def ok(args):
    r = runner.invoke(app, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    return r


@pytest.fixture(scope="module")
def seq(tmp_path_factory, tiny_capture):
    root = tmp_path_factory.mktemp("cli_avatar")
    cap = tiny_capture
    ok(["build-avatar", cap, "--out", root / "avatar", "--material", "denim"])
    ok(["animate", root / "avatar", "--motion", "twist", "--duration", "0.2", "--out", root / "seq"])
    (root / "cap").symlink_to(cap)
    return root


def test_render_orbit_and_capture_cameras(seq):
    ok(["render", seq / "seq", "--out", seq / "r", "--size", "64", "--spp", "4", "--light", "sun"])
    from PIL import Image

    frames = sorted((seq / "r" / "frames" / "orbit").glob("*.png"))
    assert len(frames) == 6 and (seq / "r" / "orbit.mp4").stat().st_size > 0
    img = np.asarray(Image.open(frames[0]))
    assert img.shape == (64, 64, 3) and img.max() > 50  # the avatar is lit and in view
    ok(["render", seq / "seq", "--out", seq / "r2", "--capture", seq / "cap", "--cameras", "cam01", "--spp", "2"])
    assert (seq / "r2" / "cam01.mp4").exists()


def test_export_usd_roundtrip(seq):
    from pxr import Usd, UsdGeom

    ok(["export", seq / "seq", "--out", seq / "a.usdc"])
    stage = Usd.Stage.Open(str(seq / "a.usdc"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/avatar/mesh"))
    z = np.load(seq / "seq" / "sequence.npz")
    assert stage.GetEndTimeCode() == len(z["vertices"]) - 1
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(3)), z["vertices"][3], atol=1e-6)


def test_bad_inputs(seq, tmp_path):
    r = runner.invoke(app, ["render", str(seq / "seq"), "--out", str(tmp_path / "x"), "--light", "disco"])
    assert r.exit_code == 2 and "disco" in r.output
    r = runner.invoke(app, ["export", str(seq / "seq"), "--out", str(tmp_path / "x.fbx")])
    assert r.exit_code == 2 and "--format" in r.output
    r = runner.invoke(app, ["animate", str(tmp_path / "nothing"), "--motion", "walk", "--out", str(tmp_path / "s")])
    assert r.exit_code == 2 and "nothing" in r.output
