"""The value objects of what stages write (physavatar.data): each round-trips through save/load
and every bad file is refused with a PhysavatarError naming it."""

import json

import numpy as np
import pytest

from physavatar.data.animated import AnimatedSequence
from physavatar.data.garment_sequence import GarmentSequence, boundary_ids
from physavatar.data.material import FittedMaterial, resolve_material
from physavatar.data.tracked import TrackedSequence
from physavatar.errors import PhysavatarError
from physavatar.files import save_npz_atomic
from physavatar.sim import PRESETS, Material

T = 3
# a body triangle pair (vertices 0-3, label 0) and a garment triangle pair (4-7, label 1)
QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
REST = np.concatenate([QUAD, QUAD + [0, 0, 0.5]])
FACES = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
LABELS = np.array([0, 0, 0, 0, 1, 1, 1, 1])


def frames(n=T, v=REST):
    return np.stack([v + [0.125 * t, 0, 0] for t in range(n)])


def same(a, b, names):
    for k in names:
        x, y = getattr(a, k), getattr(b, k)
        assert (x is None and y is None) or np.array_equal(x, y), k


def refused(fn, path, match):
    """fn() raises a PhysavatarError naming ``path`` whose problem matches ``match``."""
    with pytest.raises(PhysavatarError, match=match) as err:
        fn()
    assert err.value.path == path and str(path) in str(err.value)
    return err.value


# -- tracked.npz -------------------------------------------------------------------------------

def tracked_arrays():
    return dict(vertices=frames().astype(np.float32), faces=FACES, labels=LABELS.astype(np.uint8),
                boundary=np.array([0, 0, 0, 0, 1, 1, 0, 0], np.uint8),
                face_colors=np.full((T, len(FACES), 3), 0.5, np.float32), frames=np.arange(T, dtype=np.int64) + 10,
                log_scales=np.zeros((len(FACES), 2), np.float32), opacity_logits=np.zeros(len(FACES), np.float32),
                edge_index=np.zeros(len(FACES), np.int64), fps=np.float64(25.0))


def test_tracked_round_trip_writes_the_tracker_format(tmp_path):
    a = tracked_arrays()
    seq = TrackedSequence(a["vertices"], FACES, LABELS, a["boundary"].astype(bool), a["face_colors"], a["frames"],
                          log_scales=a["log_scales"], opacity_logits=a["opacity_logits"], edge_index=a["edge_index"],
                          fps=25.0)
    seq.save(tmp_path / "tracked.npz")
    with np.load(tmp_path / "tracked.npz") as z:  # the file track.py always wrote, array for array
        assert list(z.files) == list(a)
        for k, v in a.items():
            assert z[k].dtype == v.dtype and np.array_equal(z[k], v), k
    back = TrackedSequence.load(tmp_path, require=("vertices", "faces", "labels", "face_colors", "frames"))
    same(back, seq, ("vertices", "faces", "labels", "boundary", "face_colors", "frames", "log_scales", "opacity_logits",
                     "edge_index", "fps"))
    assert back.path == tmp_path / "tracked.npz" and back.fps == 25.0
    assert back.labels.dtype == np.int64 and back.boundary.dtype == bool and back.frames.dtype == np.int64
    # another tool's sequence, a capture's ground-truth meshes: vertices alone are enough
    save_npz_atomic(tmp_path / "meshes.npz", vertices=a["vertices"])
    only = TrackedSequence.load(tmp_path / "meshes.npz")
    assert only.faces is None and only.fps is None and np.array_equal(only.vertices, a["vertices"])


@pytest.mark.parametrize("change, require, match", [
    ({"labels": None}, ("vertices", "faces", "labels"), "missing array 'labels'"),
    ({"vertices": None}, (), "missing array 'vertices'"),
    ({"vertices": frames()[:, :, :2]}, (), r"vertices must be \[T >= 1, V=8, 3\], got \(3, 8, 2\)"),
    ({"vertices": frames()[:, :5]}, (), r"vertices must be \[T >= 1, V=8, 3\]"),
    ({"faces": FACES + 5}, (), r"faces must be \[F, 3\] indices into the vertices"),
    ({"vertices": np.where(np.arange(8)[:, None] == 3, np.nan, frames())}, (), "vertices contain non-finite values"),
    ({"boundary": np.ones(5, np.uint8)}, (), "boundary has 5 flags for 8 vertices"),
    ({"face_colors": np.zeros((T, 3, 3))}, (), r"face_colors must be \[T=3, F=4, 3\], got \(3, 3, 3\)"),
    ({"frames": np.arange(T + 1)}, (), r"frames has shape \(4,\) for 3 frames"),
    ({"fps": np.float64(0.0)}, (), "fps must be positive"),
])
def test_tracked_bad_files_are_named(tmp_path, change, require, match):
    a = tracked_arrays()
    for k, v in change.items():
        if v is None:
            del a[k]
        else:
            a[k] = v
    save_npz_atomic(tmp_path / "t" / "tracked.npz", **a)
    refused(lambda: TrackedSequence.load(tmp_path / "t", require=require), tmp_path / "t" / "tracked.npz", match)


def test_tracked_min_frames_and_missing_file(tmp_path):
    a = tracked_arrays()
    a["vertices"] = a["vertices"][:1]
    a["face_colors"], a["frames"] = a["face_colors"][:1], a["frames"][:1]
    save_npz_atomic(tmp_path / "one.npz", **a)
    assert TrackedSequence.load(tmp_path / "one.npz").n_frames == 1
    refused(lambda: TrackedSequence.load(tmp_path / "one.npz", min_frames=2), tmp_path / "one.npz",
            r"vertices must be \[T >= 2, V=8, 3\], got \(1, 8, 3\)")
    # a folder without the file is named with the file
    refused(lambda: TrackedSequence.load(tmp_path / "nothing"), tmp_path / "nothing" / "tracked.npz", "file not found")


# -- garment_sequence.npz ----------------------------------------------------------------------

def garment_arrays():
    return dict(vertices=frames(v=QUAD).astype(np.float32), faces=FACES[:2], boundary=np.array([0, 1]),
                body_vertices=frames(v=QUAD - [0, 0, 1]).astype(np.float32), body_faces=FACES[:2],
                fps=np.float64(30.0), rest_vertices=QUAD.astype(np.float32))


def test_garment_sequence_round_trip_writes_simulates_format(tmp_path):
    a = garment_arrays()
    seq = GarmentSequence(frames(v=QUAD), FACES[:2], np.array([0, 1]), frames(v=QUAD - [0, 0, 1]), FACES[:2], 30.0, QUAD)
    seq.save(tmp_path / "garment_sequence.npz")
    with np.load(tmp_path / "garment_sequence.npz") as z:
        assert list(z.files) == list(a)
        for k, v in a.items():
            assert z[k].dtype == v.dtype and np.array_equal(z[k], v), k
    back = GarmentSequence.load(tmp_path)
    assert back.path == tmp_path / "garment_sequence.npz" and back.fps == 30.0
    same(back, seq, ("vertices", "faces", "boundary", "body_vertices", "body_faces", "rest_vertices"))
    # the least a simulator writes: vertices and faces; boundary flags become ids, rest is frame 0
    save_npz_atomic(tmp_path / "min.npz", vertices=a["vertices"], faces=a["faces"], boundary=np.array([1, 0, 0, 1], bool))
    m = GarmentSequence.load(tmp_path / "min.npz")
    assert m.fps == 25.0 and m.body_vertices is None and list(m.boundary) == [0, 3]
    np.testing.assert_array_equal(m.rest_vertices, a["vertices"][0])


def test_garment_sequence_not_finite_is_written_but_not_read(tmp_path):
    V = frames(v=QUAD)
    V[2, 1] = np.nan  # simulate writes a failed frame (and says so); fit-physics refuses it
    GarmentSequence(V, FACES[:2], np.array([0])).save(tmp_path / "g.npz")
    refused(lambda: GarmentSequence.load(tmp_path / "g.npz"), tmp_path / "g.npz", "vertices contain non-finite values")


@pytest.mark.parametrize("change, match", [
    ({"faces": None}, r"missing array 'faces' \(a garment sequence needs"),
    ({"vertices": frames(v=QUAD)[:1]}, r"vertices must be \[T >= 2, N, 3\], got \(1, 4, 3\)"),
    ({"faces": np.array([[0, 1, 4]])}, r"faces must be \[F, 3\] indices into the 4 garment vertices"),
    ({"vertices": np.where(np.arange(4)[:, None] == 2, np.inf, frames(v=QUAD))}, "vertices contain non-finite values"),
    ({"boundary": np.array([0, 7])}, "boundary must be 4 flags or ids into the 4 garment vertices"),
    ({"rest_vertices": QUAD[:3]}, r"rest_vertices must be \[4, 3\] finite, got \(3, 3\)"),
    ({"body_faces": None}, "body_vertices without body_faces"),
    ({"body_vertices": frames(v=QUAD)[:2]}, r"body_vertices must be \[T=3, Nb, 3\], got \(2, 4, 3\)"),
    ({"body_faces": FACES[2:]}, r"body_faces must be \[F, 3\] indices into the body vertices"),
    ({"body_vertices": np.full((T, 4, 3), np.nan)}, "body_vertices contain non-finite values"),
    ({"fps": np.float64(-1)}, "fps must be positive, got -1.0"),
])
def test_garment_sequence_bad_files_are_named(tmp_path, change, match):
    a = garment_arrays()
    for k, v in change.items():
        if v is None:
            del a[k]
        else:
            a[k] = v
    np.savez(tmp_path / "bad.npz", **a)
    refused(lambda: GarmentSequence.load(tmp_path / "bad.npz"), tmp_path / "bad.npz", match)


def test_boundary_flags_or_ids():
    assert list(boundary_ids(np.array([True, False, True]), 3)) == [0, 2]
    assert list(boundary_ids(np.array([1, 0, 1]), 3)) == [0, 2]  # 0/1 flags, one per vertex
    assert list(boundary_ids(np.array([2, 0, 2]), 3)) == [0, 2]  # ids
    with pytest.raises(ValueError, match="3 flags or ids"):
        boundary_ids(np.array([5]), 3)


# -- material.json -----------------------------------------------------------------------------

def fit_record(material: Material) -> dict:
    """What fit-physics writes (FitResult.to_json's keys, in its order)."""
    return {"material": material.to_dict(),
            "ratios": {"stretch_ratio": {"value": material.stretch_ratio, "unit": "m^2/s^2", "symbol": "ks/rho",
                                         "interval95": [0.9 * material.stretch_ratio, 1.1 * material.stretch_ratio]},
                       "bend_ratio": {"value": material.bend_ratio, "unit": "m^3/s^2", "symbol": "kb/rho",
                                      "interval95": None}},
            "loss": 1e-4, "rms_mm": 0.5, "integrator": material.integrator, "model_selection": None, "proxy": None,
            "start_state": {"pushed_vertices": 0}}


def test_fitted_material_round_trip(tmp_path):
    mat = PRESETS["denim"]
    fit = FittedMaterial.from_json(fit_record(mat))
    fit.save(tmp_path / "material.json")
    assert list(json.loads((tmp_path / "material.json").read_text())) == list(fit_record(mat))  # order kept
    back = FittedMaterial.load(tmp_path)
    assert back == fit and back.material == mat and back.integrator == "euler"
    assert back.intervals["bend_ratio"] is None and back.intervals["stretch_ratio"][0] < mat.stretch_ratio
    assert back.start_state == {"pushed_vertices": 0}
    # the simulator reads the same file as its material
    assert Material.load(tmp_path / "material.json") == mat


@pytest.mark.parametrize("edit, match", [
    (lambda r: r.pop("material"), "not a fitted material"),
    (lambda r: r["material"].update(density=-1.0), "not a material"),
    (lambda r: r["ratios"]["stretch_ratio"].update(interval95=[2.0, 1.0]), r"ratios.stretch_ratio.interval95 must be"),
    (lambda r: r["ratios"]["bend_ratio"].update(interval95=[float("nan"), 1.0]), r"ratios.bend_ratio.interval95"),
    (lambda r: r.update(integrator="bdf2"), "integrator 'bdf2' differs from the material's 'euler'"),
])
def test_fitted_material_bad_files_are_named(tmp_path, edit, match):
    rec = fit_record(PRESETS["silk"])
    edit(rec)
    (tmp_path / "material.json").write_text(json.dumps(rec))
    refused(lambda: FittedMaterial.load(tmp_path / "material.json"), tmp_path / "material.json", match)
    (tmp_path / "broken.json").write_text("{")
    refused(lambda: FittedMaterial.load(tmp_path / "broken.json"), tmp_path / "broken.json", "cannot read material json")


def test_resolve_material(tmp_path):
    assert resolve_material("silk") is PRESETS["silk"] and resolve_material(PRESETS["denim"]) is PRESETS["denim"]
    FittedMaterial.from_json(fit_record(PRESETS["cotton"])).save(tmp_path / "fit.json")
    assert resolve_material(tmp_path / "fit.json") == PRESETS["cotton"]
    assert resolve_material(str(tmp_path / "fit.json"), option="--material") == PRESETS["cotton"]
    with pytest.raises(PhysavatarError, match="option --material: 'rubber' is not one of silk, cotton, denim or a .json"):
        resolve_material("rubber", option="--material")
    refused(lambda: resolve_material(tmp_path / "none.json"), tmp_path / "none.json", "cannot read material json")


# -- the animate folder ------------------------------------------------------------------------

def animated(uvs=True):
    uv = np.tile(np.array([[0, 0], [1, 0], [1, 1]], float), (len(FACES), 1, 1)) if uvs else None
    return AnimatedSequence(frames(), FACES, LABELS, uv, 25.0, None)


def test_animated_round_trip(tmp_path):
    seq = animated()
    seq.avatar = tmp_path / "avatar"
    seq.save(tmp_path / "seq", {"command": "test", "motion": "walk"})
    assert (tmp_path / "seq" / "meshes" / "000002.ply").is_file()
    meta = json.loads((tmp_path / "seq" / "sequence.json").read_text())
    assert meta == {"command": "test", "motion": "walk", "avatar": str(tmp_path / "avatar"), "frames": 3, "fps": 25.0}
    back = AnimatedSequence.load(tmp_path / "seq")
    np.testing.assert_array_equal(back.vertices, seq.vertices)
    np.testing.assert_array_equal(back.faces, FACES)
    np.testing.assert_array_equal(back.labels, LABELS)
    np.testing.assert_array_equal(back.face_uvs, seq.face_uvs)
    assert back.fps == 25.0 and back.avatar == tmp_path / "avatar" and back.vertices.dtype == np.float64
    animated(uvs=False).save(tmp_path / "plain", {}, ply=False)
    plain = AnimatedSequence.load(tmp_path / "plain")
    assert plain.face_uvs is None and plain.avatar is None and not (tmp_path / "plain" / "meshes").exists()


@pytest.mark.parametrize("change, match", [
    ({"labels": None}, "missing array 'labels'"),
    ({"vertices": frames()[0]}, r"vertices must be \[T >= 1, V, 3\], got \(8, 3\)"),
    ({"faces": FACES[:, :2]}, r"faces must be \[F, 3\], got \(4, 2\)"),
    ({"labels": LABELS[:5]}, r"labels has shape \(5,\) for 8 vertices"),
    ({"face_uvs": np.zeros((2, 3, 2))}, r"face_uvs must be \[F=4, 3, 2\]"),
    ({"vertices": np.where(np.arange(T)[:, None, None] == 1, np.nan, frames())}, r"non-finite values \(first in frame 1\)"),
    ({"fps": np.float64(0)}, "fps must be positive"),
])
def test_animated_bad_files_are_named(tmp_path, change, match):
    seq = animated()
    seq.save(tmp_path / "seq", {}, ply=False)
    with np.load(tmp_path / "seq" / "sequence.npz") as z:
        a = dict(z)
    for k, v in change.items():
        if v is None:
            del a[k]
        else:
            a[k] = v
    save_npz_atomic(tmp_path / "seq" / "sequence.npz", **a)
    refused(lambda: AnimatedSequence.load(tmp_path / "seq"), tmp_path / "seq" / "sequence.npz", match)


def test_animated_needs_its_meta(tmp_path):
    animated().save(tmp_path / "seq", {}, ply=False)
    (tmp_path / "seq" / "sequence.json").unlink()
    refused(lambda: AnimatedSequence.load(tmp_path / "seq"), tmp_path / "seq" / "sequence.json", "file not found")
