"""`inspect` compares each camera's mask with the template's projection: a camera off by half a
pixel, or stored in another convention, is named; so is a ground_truth/ its readers would refuse."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from physavatar.camera import Camera
from physavatar.capture import load_capture
from physavatar.capture_checks import alignment_problems, camera_alignment, shifted_silhouettes, silhouette
from physavatar.cli import app
from physavatar.data.ground_truth import ground_truth_problems

runner = CliRunner()


def _square_camera():
    """Identity camera: a point (x, y, 1) projects to pixel (x, y)."""
    return Camera("c", 10, 8, np.eye(3), np.eye(4))


def test_silhouette_covers_exactly_the_pixel_centres_inside():
    cam = _square_camera()
    x0, x1, y0, y1 = 2.3, 7.6, 1.2, 4.9
    V = np.array([[x0, y0, 1], [x1, y0, 1], [x1, y1, 1], [x0, y1, 1]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    s = silhouette(cam, V, F)
    expect = np.zeros((8, 10), bool)
    expect[2:5, 3:8] = True  # centres x 3..7, y 2..4: 15 pixels, no edge pixel leaks in
    assert np.array_equal(s, expect)
    for (dx, dy), sh in shifted_silhouettes(cam, V, F).items():
        assert np.array_equal(sh, silhouette(cam, V + [dx, dy, 0], F)), (dx, dy)


@pytest.fixture(scope="module")
def bad_captures(tmp_path_factory, tiny_capture):
    root = tmp_path_factory.mktemp("checks")
    out = {}
    for name in ("half_pixel", "c2w", "gt"):
        out[name] = root / name
        shutil.copytree(tiny_capture, out[name])
    cams = json.loads((tiny_capture / "cameras.json").read_text())
    half = [dict(c) for c in cams]
    half[1]["K"] = (np.array(half[1]["K"]) + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]).tolist()
    (out["half_pixel"] / "cameras.json").write_text(json.dumps(half))
    inv = [dict(c) for c in cams]
    inv[0]["w2c"] = np.linalg.inv(np.array(inv[0]["w2c"])).tolist()
    (out["c2w"] / "cameras.json").write_text(json.dumps(inv))
    gt = out["gt"] / "ground_truth"
    z = dict(np.load(gt / "meshes.npz"))
    z["vertices"] = z["vertices"].copy()
    z["vertices"][2, 5] = np.nan
    np.savez(gt / "meshes.npz", **z)
    (gt / "material.json").write_text("{not json")
    shutil.rmtree(next((gt / "heldout" / "masks").iterdir()))
    return out


def test_a_correct_capture_passes_and_fits_best_unmoved(tiny_capture):
    cap = load_capture(tiny_capture)
    assert alignment_problems(cap) == [] and ground_truth_problems(cap) == []
    for cam in cap.cameras:
        a = camera_alignment(cam, cap.mask(cam.name, cap.frames[0]) > 0.5, cap.template.vertices, cap.template.faces)
        assert a["best_shift"] == (0.0, 0.0) and a["iou"] > 0.9, (cam.name, a)  # 96 px, 4 spp masks


def test_half_a_pixel_and_camera_to_world_are_named(bad_captures):
    r = runner.invoke(app, ["inspect", str(bad_captures["half_pixel"])])
    assert r.exit_code == 2 and "Traceback" not in r.output
    assert "cameras.json" in r.output and "cam01" in r.output and "(-0.5, -0.5) px" in r.output, r.output
    assert "principal point" in r.output and "1 problem(s)" in r.output
    r = runner.invoke(app, ["inspect", str(bad_captures["c2w"])])
    assert r.exit_code == 2 and "cam00" in r.output and "camera-to-world" in r.output, r.output


def test_broken_ground_truth_is_listed(bad_captures):
    r = runner.invoke(app, ["inspect", str(bad_captures["gt"])])
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    out = " ".join(r.output.split())
    assert "meshes.npz" in out and "NaN or infinite vertices in 1 frame(s) (first: 2)" in out, out
    assert "material.json" in out and "masks" in out and "3 problem(s)" in out, out
