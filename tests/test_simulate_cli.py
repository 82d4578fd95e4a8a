"""`physavatar simulate`: the three input modes, no intersections, clear errors."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from physavatar.cli import app
from physavatar.files import PlyMesh, write_ply
from physavatar.geometry import count_intersections

runner = CliRunner()


@pytest.fixture(scope="module")
def skirt_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "skirt"
    r = runner.invoke(app, ["simulate", "--garment", "skirt", "--motion", "twist", "--duration", "0.4",
                            "--edge-length", "0.05", "--out", str(out), "--no-preview"])
    assert r.exit_code == 0, r.output
    return out


def write_collider_and_garment(folder, z, frames, garment_vertices):
    """The body of a simulate run as a folder of PLY frames (folder/body), and a garment
    (folder/garment.ply) with its boundary flags."""
    for t in range(frames):
        write_ply(folder / "body" / f"f{t:03d}.ply", PlyMesh(z["body_vertices"][t], z["body_faces"]))
    flag = np.zeros(len(garment_vertices), np.uint8)
    flag[z["boundary"]] = 1
    write_ply(folder / "garment.ply", PlyMesh(garment_vertices, z["faces"], {"boundary": flag}))


def test_garment_on_builtin_motion(skirt_run):
    z = np.load(skirt_run / "garment_sequence.npz")
    X, B = z["vertices"].astype(float), z["body_vertices"].astype(float)
    assert X.shape[0] == 11 and np.isfinite(X).all()
    for t in range(X.shape[0]):
        assert count_intersections(X[t], z["faces"], B[t], z["body_faces"]) == 0
    # the command checked every frame itself and says so
    assert json.loads((skirt_run / "config.json").read_text())["frames_with_intersection_or_nan"] == []
    # boundary (waistband) vertices stay on the body: they move with the twisting hips
    b = z["boundary"]
    assert np.linalg.norm(X[-1, b] - X[0, b], axis=1).max() > 0.01
    assert (skirt_run / "meshes" / "000010.ply").exists() and (skirt_run / "material.json").exists()


def test_collider_sequence_and_garment_file(skirt_run, tmp_path):
    z = np.load(skirt_run / "garment_sequence.npz")
    # the body as a folder of PLY frames from "another tool", the garment as a PLY with boundary flags
    write_collider_and_garment(tmp_path, z, 4, z["vertices"][0])
    r = runner.invoke(app, ["simulate", "--collider", str(tmp_path / "body"), "--garment", str(tmp_path / "garment.ply"),
                            "--out", str(tmp_path / "o"), "--no-preview"])
    assert r.exit_code == 0, r.output
    X = np.load(tmp_path / "o" / "garment_sequence.npz")["vertices"]
    # same body motion and garment -> the same simulation as the first run's first frames, up to
    # the float32 rounding of the files and the Newton tolerance (1e-3 m/s x 0.04 s)
    assert np.abs(X - z["vertices"][:4]).max() < 1e-3


def test_bad_inputs_exit_2(tmp_path):
    write_ply(tmp_path / "a" / "0.ply", PlyMesh(np.random.rand(4, 3), [[0, 1, 2]]))
    write_ply(tmp_path / "a" / "1.ply", PlyMesh(np.random.rand(5, 3), [[0, 1, 2]]))
    write_ply(tmp_path / "g.ply", PlyMesh(np.random.rand(3, 3), [[0, 1, 2]], {"boundary": np.ones(3, np.uint8)}))
    r = runner.invoke(app, ["simulate", "--collider", str(tmp_path / "a"), "--garment", str(tmp_path / "g.ply"),
                            "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "1.ply" in r.output and "Traceback" not in r.output
    r = runner.invoke(app, ["simulate", "--garment", "skirt", "--motion", "walk", "--material", "rubber",
                            "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "rubber" in r.output
    r = runner.invoke(app, ["simulate", "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "say what to simulate" in r.output
    r = runner.invoke(app, ["simulate", "--garment", "skirt", "--motion", "walk", "--integrator", "rk4",
                            "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "--integrator" in r.output and "Traceback" not in r.output
    for cmd in (["simulate", "--garment", "skirt", "--motion", "walk"], ["animate", str(tmp_path / "avatar")]):
        # the garment-file options are declared once (stages.garment_file.GarmentFileOptions): same checks
        r = runner.invoke(app, [*cmd, "--repair-limit", "-0.01", "--out", str(tmp_path / "o")])
        assert r.exit_code == 2 and "--repair-limit" in r.output and ">= 0" in r.output, r.output
    assert not (tmp_path / "o").exists()


def test_motion_starting_away_from_rest_is_reached_by_a_warmup(tmp_path):
    """A clip that starts mid-motion (as a BVH clip does) would put the body through the garment
    made for the rest pose: the command eases into it first and writes only the clip's frames."""
    from physavatar.body import BodyModel, Motion, builtin_motion

    walk = builtin_motion("twist", BodyModel(topology="collider").bone_names, 25.0, 1.0)
    k = 12  # mid-twist: far from the rest pose
    assert np.abs(walk.rotations[k]).max() > 0.2
    Motion("clip", 25.0, walk.bone_names, walk.rotations[k:k + 4], walk.root_translation[k:k + 4]).save(tmp_path / "clip.npz")
    r = runner.invoke(app, ["simulate", "--garment", "skirt", "--motion", str(tmp_path / "clip.npz"), "--warmup", "0.2",
                            "--edge-length", "0.05", "--out", str(tmp_path / "o"), "--no-preview"])
    assert r.exit_code == 0, r.output
    cfg = json.loads((tmp_path / "o" / "config.json").read_text())
    assert cfg["warmup_frames"] == 5 and cfg["frames"] == 4 and cfg["frames_with_intersection_or_nan"] == []
    z = np.load(tmp_path / "o" / "garment_sequence.npz")
    assert z["vertices"].shape[0] == 4
    for t in range(4):
        assert count_intersections(z["vertices"][t], z["faces"], z["body_vertices"][t], z["body_faces"]) == 0


def test_garment_crossing_the_first_collider_frame_beyond_the_repair_limit_is_refused(skirt_run, tmp_path):
    z = np.load(skirt_run / "garment_sequence.npz")
    V = z["vertices"][0].astype(float)
    V[:, :2] *= 0.5  # shrunk through the hips
    write_collider_and_garment(tmp_path, z, 2, V)
    r = runner.invoke(app, ["simulate", "--collider", str(tmp_path / "body"), "--garment", str(tmp_path / "garment.ply"),
                            "--out", str(tmp_path / "o"), "--no-preview"])
    assert r.exit_code == 2 and "repair limit" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "o" / "garment_sequence.npz").exists()


def test_fit_physics_reads_a_simulated_sequence_back(skirt_run, tmp_path):
    """simulate's folder (garment_sequence.npz: garment, boundary, body, fps, rest shape) is an
    input of fit-physics as it is: started from the material that made it, the fit's simulation
    reproduces the sequence (which needs the rest shape, boundary, body and fps read right)."""
    from physavatar.stages.physics.data import load_physics_data

    z = np.load(skirt_run / "garment_sequence.npz")
    data = load_physics_data(skirt_run)
    assert data.reference.shape == z["vertices"].shape and np.array_equal(data.boundary, z["boundary"])
    assert data.collider.shape == z["body_vertices"].shape and data.fps == float(z["fps"])
    np.testing.assert_array_equal(data.rest, z["rest_vertices"].astype(float))
    r = runner.invoke(app, ["fit-physics", str(skirt_run), "--out", str(tmp_path / "fit"), "--init",
                            str(skirt_run / "material.json"), "--window", "5", "--iterations", "1",
                            "--integrator", "euler", "--newton-tol", "1e-3"])
    assert r.exit_code == 0, r.output
    fit = json.loads((tmp_path / "fit" / "material.json").read_text())
    assert fit["initial_rms_mm"] < 0.5 and fit["window_frames"] == 5
    # the same file given by name, and a broken one
    assert load_physics_data(skirt_run / "garment_sequence.npz").reference.shape == data.reference.shape
    bad = dict(z)
    bad["body_vertices"] = bad["body_vertices"][:3]
    np.savez(tmp_path / "bad.npz", **bad)
    r = runner.invoke(app, ["fit-physics", str(tmp_path / "bad.npz"), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "bad.npz" in r.output and "body_vertices must be [T=11" in r.output, r.output


def test_a_garment_sequence_is_collider_and_garment_of_simulate(skirt_run, tmp_path):
    """garment_sequence.npz as --collider (its body) and --garment (its rest shape and boundary):
    simulate re-runs the same sequence."""
    seq = skirt_run / "garment_sequence.npz"
    r = runner.invoke(app, ["simulate", "--collider", str(seq), "--garment", str(seq), "--out", str(tmp_path / "o"),
                            "--no-preview"])
    assert r.exit_code == 0, r.output
    X = np.load(tmp_path / "o" / "garment_sequence.npz")["vertices"]
    z = np.load(seq)
    assert X.shape == z["vertices"].shape
    # as in test_collider_sequence_and_garment_file: float32 files and the Newton tolerance, which
    # the contact-rich twist amplifies steadily (0.1 mm at frame 3, 2 mm at frame 10 when written)
    assert np.abs(X[:4] - z["vertices"][:4]).max() < 1e-3 and np.abs(X - z["vertices"]).max() < 5e-3
