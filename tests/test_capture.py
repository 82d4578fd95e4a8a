"""Capture folder: a valid one loads; every broken case gives one message naming the file, exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from capture_factory import BONES, make_capture
from physavatar.capture import load_capture, summarize, validate_capture
from physavatar.cli import app
from physavatar.errors import CaptureError
from physavatar.files import read_ply, write_ply

runner = CliRunner()


@pytest.fixture
def cap(tmp_path) -> Path:
    return make_capture(tmp_path / "cap")


def snapshot(root: Path) -> dict:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


def inspect(root: Path):
    return runner.invoke(app, ["inspect", str(root)])


def test_valid_capture_loads_and_summarizes(cap):
    c = load_capture(cap, deep=True)
    s = summarize(c)
    assert s["cameras"] == 2 and s["frames"] == 3 and s["resolution"] == "32x24"
    assert s["template_vertices"] == 162 + 80 and s["garment_vertices"] == 80
    assert s["boundary_vertices"] == 16 and s["uvs"] and s["masks"]
    img = c.image("cam00", 1)
    assert img.shape == (24, 32, 3) and img.dtype == np.float32
    before = snapshot(cap)
    r = inspect(cap)
    assert r.exit_code == 0, r.output
    assert "garment vertices" in r.output and "80" in r.output
    assert snapshot(cap) == before  # nothing is ever written into a capture folder


def expect_error(root: Path, file_part: str, words: str):
    r = inspect(root)
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    assert file_part in r.output, r.output
    assert words.lower() in r.output.lower(), r.output
    with pytest.raises(CaptureError):
        load_capture(root, deep=True)


def test_missing_file(cap):
    (cap / "cameras.json").unlink()
    expect_error(cap, "cameras.json", "not found")


def test_missing_folder(tmp_path):
    expect_error(tmp_path / "nope", "nope", "not found")


def test_corrupt_image(cap):
    p = cap / "images" / "cam01" / "000002.png"
    p.write_bytes(p.read_bytes()[:40])
    expect_error(cap, "000002.png", "corrupt")


def test_not_an_image(cap):
    (cap / "images" / "cam00" / "000000.png").write_text("hello")
    expect_error(cap, "000000.png", "corrupt")


def test_image_size_mismatch(cap):
    from physavatar.capture import save_png

    save_png(cap / "images" / "cam00" / "000001.png", np.zeros((10, 10, 3)))
    expect_error(cap, "000001.png", "10x10 but camera")


def test_camera_not_finite(cap):
    cams = json.loads((cap / "cameras.json").read_text())
    cams[1]["w2c"][0][3] = float("nan")
    (cap / "cameras.json").write_text(json.dumps(cams).replace("NaN", "NaN"))
    expect_error(cap, "cameras.json", "NaN")


def test_camera_not_rigid(cap):
    cams = json.loads((cap / "cameras.json").read_text())
    cams[0]["w2c"][0][0] *= 2.0
    (cap / "cameras.json").write_text(json.dumps(cams))
    expect_error(cap, "cameras.json", "not a rotation")


def test_frames_missing_for_a_camera(cap):
    (cap / "images" / "cam01" / "000001.png").unlink()
    expect_error(cap, "cam01", "1 of 3 frames missing")


def test_pose_wrong_shape(cap):
    z = dict(np.load(cap / "body.npz"))
    z["rotations"] = np.zeros((3, len(BONES), 4))
    np.savez(cap / "body.npz", **z)
    expect_error(cap, "body.npz", "rotations")


def test_pose_frame_count(cap):
    z = dict(np.load(cap / "body.npz"))
    z["rotations"] = np.zeros((5, len(BONES), 3))
    z["root_translation"] = np.zeros((5, 3))
    np.savez(cap / "body.npz", **z)
    expect_error(cap, "body.npz", "5 frames but capture.json lists 3")


def test_pose_nan(cap):
    z = dict(np.load(cap / "body.npz"))
    z["rotations"][1, 2, 0] = np.nan
    np.savez(cap / "body.npz", **z)
    expect_error(cap, "body.npz", "NaN")


def _edit_template(cap, fn):
    p = cap / "template" / "mesh.ply"
    m = read_ply(p)
    fn(m)
    write_ply(p, m)


def test_template_non_manifold(cap):
    def fn(m):
        # a third face on an existing edge
        a, b = m.faces[0, 0], m.faces[0, 1]
        m.vertices = np.concatenate([m.vertices, [[5.0, 5.0, 5.0]]])
        for k in m.vertex_data:
            m.vertex_data[k] = np.concatenate([m.vertex_data[k], m.vertex_data[k][:1]])
        m.faces = np.concatenate([m.faces, [[a, b, len(m.vertices) - 1]]])
        m.face_uvs = np.concatenate([m.face_uvs, m.face_uvs[:1]])
    _edit_template(cap, fn)
    expect_error(cap, "mesh.ply", "non-manifold")


def test_template_degenerate_faces(cap):
    def fn(m):
        f = m.faces[5]
        m.vertices[f[1]] = m.vertices[f[0]]  # collapse an edge: zero-area faces
    _edit_template(cap, fn)
    expect_error(cap, "mesh.ply", "degenerate")


def test_labels_out_of_range(cap):
    def fn(m):
        m.vertex_data["label"] = m.vertex_data["label"].copy()
        m.vertex_data["label"][-1] = 99
    _edit_template(cap, fn)
    expect_error(cap, "mesh.ply", "labels out of range")


def test_garment_without_boundary(cap):
    def fn(m):
        m.vertex_data["boundary"] = np.zeros_like(m.vertex_data["boundary"])
    _edit_template(cap, fn)
    expect_error(cap, "mesh.ply", "no boundary vertices")


def test_corrupt_template(cap):
    (cap / "template" / "mesh.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2")
    expect_error(cap, "mesh.ply", "PLY")


def test_bad_capture_json(cap):
    (cap / "capture.json").write_text("{ not json")
    expect_error(cap, "capture.json", "JSON")


def test_all_problems_are_listed(cap):
    (cap / "images" / "cam01" / "000001.png").unlink()
    z = dict(np.load(cap / "body.npz"))
    z["rotations"][0, 0, 0] = np.nan
    np.savez(cap / "body.npz", **z)
    problems = validate_capture(cap)
    files = {p.path.name for p in problems}
    assert {"body.npz", "cam01"} <= files
    r = inspect(cap)
    assert r.exit_code == 2 and "2 problem(s)" in r.output


def test_garment_rest_shape_in_the_template(cap, tmp_path):
    """template/mesh.ply's optional rest_x/y/z: read back exactly, used as the garment's rest shape
    by the simulator's split and by fit-physics' data, and checked (partial, NaN, degenerate)."""
    from physavatar.garment_sim import split_template
    from physavatar.stages.physics.data import load_physics_data

    c = load_capture(cap)
    assert c.template.rest is None and c.template.rest_shape is c.template.vertices
    t = c.template
    rest = t.vertices.copy()
    g = t.labels > 0
    rest[g] = t.vertices[g].mean(0) + 0.9 * (t.vertices[g] - t.vertices[g].mean(0))  # a garment 10 % smaller at rest
    from physavatar.capture import Template

    Template(t.vertices, t.faces, t.labels, t.boundary, t.face_uvs, rest).save(cap / "template" / "mesh.ply")
    c2 = load_capture(cap)
    assert np.allclose(c2.template.rest, rest, atol=1e-6)  # float32 in the PLY
    _, _, part = split_template(c2.template.vertices, c2.template.faces, c2.template.labels, c2.template.boundary,
                                c2.template.rest)
    assert np.allclose(part.rest_shape, rest[g], atol=1e-6) and np.allclose(part.vertices, t.vertices[g], atol=1e-6)
    # fit-physics on a capture's true meshes takes the rest shape from the template
    gt = np.repeat(t.vertices[None], 3, axis=0)
    (cap / "ground_truth").mkdir()
    np.savez(cap / "ground_truth" / "meshes.npz", vertices=gt, faces=t.faces, labels=t.labels)
    data = load_physics_data(cap)
    assert np.allclose(data.rest, rest[g], atol=1e-6)
    # bad rest shapes: one line each
    p = cap / "template" / "mesh.ply"
    ply = read_ply(p)
    orig = dict(ply.vertex_data)
    for change, words in ((lambda d: d.pop("rest_z"), "needs all of"),
                          (lambda d: d["rest_x"].__setitem__(np.flatnonzero(g)[0], np.nan), "NaN"),
                          (lambda d: [d[k].__setitem__(np.flatnonzero(g), 0.0) for k in ("rest_x", "rest_y", "rest_z")],
                           "degenerate in the rest shape")):
        data = {k: np.array(v, copy=True) for k, v in orig.items()}
        change(data)
        ply.vertex_data = data
        write_ply(p, ply)
        expect_error(cap, "mesh.ply", words)
