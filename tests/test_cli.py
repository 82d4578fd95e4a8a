"""The command-line tool: help lists working commands; pose writes a posed sequence; bad options exit 2."""

import numpy as np
from typer.testing import CliRunner

from physavatar.cli import app
from physavatar.files import read_ply

runner = CliRunner()


def test_help_lists_commands():
    r = runner.invoke(app, ["--help"])
    assert r.exit_code == 0
    for cmd in ("inspect", "motion", "pose"):
        assert cmd in r.output


def test_pose_writes_sequence(tmp_path):
    out = tmp_path / "p"
    r = runner.invoke(app, ["pose", "--motion", "jump", "--duration", "0.4", "--topology", "tiny",
                            "--out", str(out), "--no-preview", "--shape", "height=0.8"])
    assert r.exit_code == 0, r.output
    z = np.load(out / "body_sequence.npz")
    assert z["vertices"].shape == (11, 369, 3)
    m = read_ply(out / "meshes" / "000010.ply")
    assert np.allclose(m.vertices, z["vertices"][10], atol=1e-5)
    assert (out / "config.json").exists()


def test_bad_options_exit_2(tmp_path):
    r = runner.invoke(app, ["pose", "--motion", "nonexistent", "--out", str(tmp_path / "x"), "--topology", "tiny"])
    assert r.exit_code == 2 and "nonexistent" in r.output and "Traceback" not in r.output
    r = runner.invoke(app, ["pose", "--shape", "height=3", "--out", str(tmp_path / "x"), "--topology", "tiny"])
    assert r.exit_code == 2 and "height" in r.output
    r = runner.invoke(app, ["motion", "preview", "walk", "--out", str(tmp_path / "x.avi")])
    assert r.exit_code == 2 and ".mp4 or .gif" in r.output


def test_motion_preview_gif(tmp_path):
    r = runner.invoke(app, ["motion", "preview", "twist", "--duration", "0.2", "--out", str(tmp_path / "t.gif")])
    assert r.exit_code == 0, r.output
    import imageio.v2 as imageio

    frames = imageio.mimread(tmp_path / "t.gif")
    assert len(frames) == 6
    assert np.asarray(frames[3]).std() > 5  # a picture, not a blank
