"""physavatar prepare (stages/prepare): each step against an independent truth, the round trip on
the tiny synthetic capture, and bad input (one line naming the file)."""

from __future__ import annotations

import itertools
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from physavatar.camera import ring_rig
from physavatar.capture import (
    CaptureError,
    is_unprepared,
    load_capture,
    unprepared_parts,
)
from physavatar.errors import PhysavatarError
from physavatar.stages.prepare import PrepareConfig
from physavatar.stages.prepare import run as prepare
from physavatar.stages.prepare.config import (
    MaskConfig,
    MeshConfig,
)
from physavatar.stages.prepare.masks import camera_masks, mask_iou, reliability, unreliable_warning
from physavatar.stages.prepare.mesh import (
    make_manifold,
    reconstruct,
    remesh,
    surface_distance,
)
from physavatar.stages.prepare.segment import garment_pieces, graph_cut, join_parts, transfer_labels
from physavatar.stages.prepare.uv import atlas

# Small budgets: the tiny capture is 96 px wide (2.3 cm per pixel at the body).
FAST = PrepareConfig(mesh=MeshConfig(voxel=0.012, edge_length=0.035), report=False)


def unprepared(src: Path, dst: Path, masks: bool = True) -> Path:
    """Hard-linked copy of a capture without template/ (and masks/)."""
    dst.mkdir(parents=True)
    for p in src.iterdir():
        if p.name == "template" or (p.name == "masks" and not masks):
            continue
        if p.is_dir():
            shutil.copytree(p, dst / p.name, copy_function=os.link)
        else:
            os.link(p, dst / p.name)
    return dst


# -- single steps against independent truths -----------------------------------------------------

def test_graph_cut_is_the_minimum_labelling():
    """The max-flow cut equals the exhaustive minimum of unary + cut edge costs on a small graph."""
    rng = np.random.default_rng(0)
    n = 9
    edges = np.array([(i, j) for i, j in itertools.combinations(range(n), 2) if rng.random() < 0.4])
    w = rng.uniform(0.1, 1.0, len(edges))
    cf, cb = rng.uniform(0, 2, n), rng.uniform(0, 2, n)

    def energy(fg):
        return (np.where(fg, cf, cb).sum() + w[fg[edges[:, 0]] != fg[edges[:, 1]]].sum())

    best = min(energy(np.array(bits, bool)) for bits in itertools.product([0, 1], repeat=n))
    got = graph_cut(cf, cb, edges, w)
    assert energy(got) == pytest.approx(best, abs=5e-3 * n)


def _grid(nx: int, ny: int, h: float = 0.01):
    """A flat triangulated grid of nx x ny vertices (spacing h) in the plane z = 1."""
    x, y = np.meshgrid(np.arange(nx) * h, np.arange(ny) * h, indexing="ij")
    V = np.stack([x.ravel(), y.ravel(), np.ones(nx * ny)], 1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return V, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_a_strap_broken_at_one_vertex_is_cut_out_whole():
    """A garment panel (rows 0-9) with a strap two vertices wide (rows 10-19) that the
    segmentation broke at one vertex of each of its columns' rows: join_parts adds the vertices that
    touch both parts (and only those), and the cut garment reaches the strap's top as one piece;
    a notch in the panel's own outline (touching one part only) is left as it is."""
    nx, ny = 20, 20
    V, F = _grid(nx, ny)
    i, j = np.divmod(np.arange(nx * ny), ny)
    garment = (i < 10) | ((i >= 10) & (j >= 8) & (j <= 9))
    broken = garment & ~((i == 12) & (j >= 8) & (j <= 9))  # the strap cut across at row 12
    notch = (i == 9) & (j == 3)
    broken &= ~notch
    joined = join_parts(broken, F)
    added = np.flatnonzero(joined & ~broken)
    assert set(added.tolist()) <= set(np.flatnonzero((i == 12) & (j >= 7) & (j <= 10)).tolist())
    assert (joined[(i == 12) & (j >= 8) & (j <= 9)]).all()
    assert not joined[notch].any()
    from scipy.sparse.csgraph import connected_components
    import trimesh

    from physavatar.geometry.mesh import adjacency

    assert connected_components(adjacency(F, len(V))[broken][:, broken], directed=False)[0] == 2
    labels = broken.astype(np.int64)
    body = trimesh.creation.icosphere(2, radius=0.1)  # a body far below: nothing is pushed
    pieces = garment_pieces(V, F, labels, body.vertices - [0, 0, 2.0], np.asarray(body.faces), min_share=0.05)
    assert len(pieces) == 1
    g, Vg, Fg = pieces[0]
    assert np.isclose(Vg[:, 0].max(), 0.19)  # the strap's top row is in the garment
    assert np.allclose(Vg[:, 2], 1.0)


def test_remesh_reaches_target_edge_on_a_sphere():
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    V, F = remesh(np.asarray(s.vertices), np.asarray(s.faces), MeshConfig(edge_length=0.05))
    e = np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1)
    assert abs(np.mean(e) / 0.05 - 1) < 0.25 and np.std(e) / np.mean(e) < 0.3
    assert np.abs(np.linalg.norm(V, axis=1) - 0.3).max() < 0.003  # stays on the sphere


def test_visual_hull_of_a_sphere():
    """Anti-aliased masks of a sphere (the pixel ray's distance to its centre) seen by 8 cameras:
    the hull surface lies on it, outside by at most the known excess between the views."""
    cams = ring_rig(6, 2.5, 1.0, (0, 0, 1.0), 120, 120, 40.0, n_elevated=2, elevated_height=2.6)
    r, c0 = 0.25, np.array([0, 0, 1.0])
    masks = {}
    for c in cams:
        o, d = c.pixel_rays()
        t = ((c0 - o) * d).sum(-1)
        dist = np.linalg.norm(o + t[..., None] * d - c0, axis=-1)
        pix = np.linalg.norm(c0 - o) / c.K[0, 0]
        masks[c.name] = np.clip((r - dist) / pix + 0.5, 0, 1)
    V, _ = reconstruct(cams, masks, MeshConfig(voxel=0.01, edge_length=0.03))
    d = np.linalg.norm(V - c0, axis=1) - r
    # At the ring's height the hull is the intersection of the 6 cameras' wedges, whose tangent
    # points lie at ±(90° - asin(r / D)) from each camera's direction: the widest gap between
    # tangent points, g, puts the polygon's corner r (1 / cos(g / 2) - 1) outside the sphere.
    D = 2.5
    th = np.degrees(np.pi / 2 - np.arcsin(r / D))
    pts = np.sort(np.array([(60 * k + s * th) % 360 for k in range(6) for s in (-1, 1)]))
    gap = np.radians(np.max(np.diff(np.concatenate([pts, pts[:1] + 360]))))
    excess = r * (1 / np.cos(gap / 2) - 1)
    ring = np.abs(V[:, 2] - c0[2]) < 0.03
    assert d.mean() < 0.006 and d.min() > -0.006, (d.mean(), d.min())
    assert excess * 0.6 < d[ring].max() < excess + 0.004, (d[ring].max(), excess)


def test_manifold_refuses_a_pinched_surface_in_one_line():
    """A strip bent round until its ends touch at one vertex: one piece, two sheets at that vertex,
    which no merging, dropping or orienting repairs."""
    n = 5
    ang = np.linspace(0, 1.5 * np.pi, n)
    B = np.stack([np.cos(ang), np.sin(ang), 0 * ang], 1)
    V = np.concatenate([B, B + [0, 0, 1]])
    F = np.array([f for i in range(n - 1) for f in ([i, i + 1, n + i + 1], [i, n + i + 1, n + i])])
    F[F == 2 * n - 1] = 0  # the strip's last top corner is its first bottom corner
    with pytest.raises(PhysavatarError) as e:
        make_manifold(V, F, Path("scan.ply"))
    assert "scan.ply" in str(e.value) and "cannot be made manifold" in str(e.value) and "\n" not in str(e.value)
    # a fin (three faces on one edge) is repaired: the largest piece is kept
    V2 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    _, F2 = make_manifold(V2, np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))
    assert len(F2) == 1


def test_atlas_gives_corner_uvs_in_the_unit_square():
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=2)
    uv = atlas(np.asarray(s.vertices), np.asarray(s.faces))
    assert uv.shape == (len(s.faces), 3, 2) and uv.min() >= 0 and uv.max() <= 1
    area = 0.5 * np.abs(np.cross(uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]))
    assert (area > 0).mean() > 0.99  # every face gets its own chart area


def test_masks_without_plate_match_the_rendered_alpha(tiny_capture):
    cap = load_capture(tiny_capture)
    ious, info = [], {}
    for c in cap.cameras[:2]:
        ms, info[c.name] = camera_masks([cap.image_path(c.name, f) for f in cap.frames], MaskConfig())
        ious += [mask_iou(m, cap.mask(c.name, f)) for m, f in zip(ms, cap.frames)]
        info[c.name] |= reliability(ms)
    assert np.mean(ious) > 0.88, np.mean(ious)  # 96 px images: the edge pixels are a large share
    assert unreliable_warning(info, MaskConfig()) is None, info  # a clean backdrop: no warning


def test_masks_with_a_background_plate(tiny_capture, tmp_path):
    """A plate differs from the frames only where the person is: the masks follow the alpha."""
    cap = load_capture(tiny_capture)
    c = cap.cameras[0]
    plate = tmp_path / "plate.png"
    from physavatar.capture import save_png

    save_png(plate, np.zeros((c.height, c.width, 3)))  # the synthetic background is black
    ms, info = camera_masks([cap.image_path(c.name, f) for f in cap.frames[:3]], MaskConfig(), plate)
    assert info["background"] == "plate"
    assert np.mean([mask_iou(m, cap.mask(c.name, f)) for m, f in zip(ms, cap.frames)]) > 0.88


def test_masks_in_a_cluttered_room_are_not_erased(tmp_path):
    """A room, not a backdrop: the background is a patchwork of six colours (the border shows them
    all), a person-sized block of another colour moves across it. The border rule (a pixel near a
    border colour is background) would take the block for background at the threshold such a
    varied border gives (3x its scatter): it is not used, and the temporal median finds the block."""
    from physavatar.capture import save_png

    rng = np.random.default_rng(0)
    H, W = 64, 48
    palette = np.array([[0.2, 0.3, 0.6], [0.5, 0.5, 0.5], [0.8, 0.75, 0.7], [0.1, 0.1, 0.1], [0.6, 0.2, 0.2],
                        [0.3, 0.6, 0.3]])
    tiles = rng.integers(0, len(palette), (H // 4, W // 4))
    room = palette[np.kron(tiles, np.ones((4, 4), int))] + rng.normal(0, 0.04, (H, W, 3))
    paths, truth = [], []
    for t in range(9):
        im = room.copy()
        m = np.zeros((H, W), bool)
        m[20:50, 4 + 4 * t:14 + 4 * t] = True
        im[m] = [0.85, 0.6, 0.5]  # skin: within 0.15 of the wall colour [0.8, 0.75, 0.7]
        p = tmp_path / f"{t:06d}.png"
        save_png(p, np.clip(im, 0, 1))
        paths.append(p)
        truth.append(m)
    ms, info = camera_masks(paths, MaskConfig())
    assert info["background"] == "temporal median"
    iou = np.mean([mask_iou(m, tm) for m, tm in zip(ms, truth)])
    assert iou > 0.8, iou
    # the border rule alone (allowed at any threshold) erases the person
    ms_b, info_b = camera_masks(paths, MaskConfig(border_max_threshold=1.0))
    assert info_b["background"] == "border colours"
    assert np.mean([mask_iou(m, tm) for m, tm in zip(ms_b, truth)]) < 0.5


def test_mask_method_resolution(tmp_path, monkeypatch):
    """auto: differencing when every camera has a plate, else MediaPipe's segmentation when it is
    installed, else differencing; --mask-method mediapipe without it is one clear error."""
    from types import SimpleNamespace

    from physavatar.capture import save_png
    from physavatar.stages.prepare import keypoints
    from physavatar.stages.prepare.masks import mask_method

    cams = [SimpleNamespace(name="a"), SimpleNamespace(name="b")]
    monkeypatch.setattr(keypoints, "mediapipe_available", lambda: None)
    assert mask_method(tmp_path, cams, MaskConfig()) == "mediapipe"
    for c in cams:
        save_png(tmp_path / "background" / f"{c.name}.png", np.zeros((4, 4, 3)))
    assert mask_method(tmp_path, cams, MaskConfig()) == "difference"
    assert mask_method(tmp_path, cams, MaskConfig(method="mediapipe")) == "mediapipe"
    monkeypatch.setattr(keypoints, "mediapipe_available", lambda: "mediapipe is not installed")
    (tmp_path / "background" / "b.png").unlink()
    assert mask_method(tmp_path, cams, MaskConfig()) == "difference"
    with pytest.raises(PhysavatarError, match="mediapipe is not installed"):
        mask_method(tmp_path, cams, MaskConfig(method="mediapipe"))


@pytest.mark.skipif(not __import__("importlib").util.find_spec("mediapipe"), reason="the keypoints extra (mediapipe)")
def test_mediapipe_masks_on_the_tiny_capture(tiny_capture):
    """MediaPipe's person segmentation against the rendered alpha (96 px: a loose bound)."""
    from physavatar.stages.prepare.masks import segmentation_masks

    cap = load_capture(tiny_capture)
    c = cap.cameras[0]
    ms, info = segmentation_masks([cap.image_path(c.name, f) for f in cap.frames[:2]], MaskConfig())
    assert np.mean([mask_iou(m, cap.mask(c.name, f)) for m, f in zip(ms, cap.frames)]) > 0.5


# -- the round trip ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def prepared_tiny(tiny_capture, tmp_path_factory):
    src = unprepared(tiny_capture, tmp_path_factory.mktemp("prep") / "in")
    out = src.parent / "out"
    prepare(src, out=out, config=FAST, progress=False)
    return out


def test_unprepared_capture_is_named_in_one_line(tiny_capture, tmp_path):
    src = unprepared(tiny_capture, tmp_path / "in")
    assert is_unprepared(src) and unprepared_parts(src) == ["template/mesh.ply"]
    with pytest.raises(CaptureError) as e:
        load_capture(src)
    assert "unprepared capture" in str(e.value) and "physavatar prepare" in str(e.value)
    assert not is_unprepared(tiny_capture)


def test_prepared_tiny_round_trip(prepared_tiny, tiny_capture):
    import json

    from physavatar.files import load_npz

    cap = load_capture(prepared_tiny, deep=True)  # what inspect and run read
    truth = load_capture(tiny_capture)
    t = cap.template
    assert t.face_uvs is not None and t.boundary.any() and (t.labels > 0).any()
    # the body part is the Anny mesh of the first frame (same vertices as the truth's body)
    assert np.allclose(t.vertices[t.labels == 0], truth.template.vertices[truth.template.labels == 0], atol=1e-5)
    z = load_npz(prepared_tiny / "prepare" / "first_frame_mesh.npz")
    d = surface_distance(z["vertices"], truth.template.vertices, truth.template.faces)
    assert np.median(d) < 0.015  # 4 cameras of 96 px: a coarse hull
    true = transfer_labels(z["vertices"], truth.template.vertices, truth.template.faces, truth.template.labels)
    acc = ((z["labels"] > 0) == (true > 0)).mean()
    assert acc > 0.6, acc
    # the true garment is covered
    assert ((z["labels"] > 0) & (true > 0)).sum() > 0.9 * (true > 0).sum()
    # the ground truth's per-vertex tracks follow the prepared template
    gt = load_npz(prepared_tiny / "ground_truth" / "meshes.npz")
    assert gt["vertices"].shape[1] == len(t.vertices)
    assert np.abs(gt["vertices"][0][t.labels == 0] - t.vertices[t.labels == 0]).max() < 1e-4
    # and so do the held-out motion's: the body copied, the garment on the true garment surface
    held = load_npz(prepared_tiny / "ground_truth" / "heldout" / "meshes.npz")
    orig = load_npz(tiny_capture / "ground_truth" / "heldout" / "meshes.npz")
    assert held["vertices"].shape == (len(orig["vertices"]), len(t.vertices), 3)
    assert np.abs(held["vertices"][:, t.labels == 0] - orig["vertices"][:, orig["labels"] == 0]).max() < 1e-5
    og = (orig["labels"][orig["faces"]] > 0).all(1)
    d = surface_distance(held["vertices"][-1][t.labels > 0].astype(np.float64), orig["vertices"][-1].astype(np.float64),
                         orig["faces"][og])
    assert d.max() < 1e-4, d.max()
    info = json.loads((prepared_tiny / "prepare.json").read_text())
    assert info["steps"]["masks"] == "given" and info["steps"]["body"] == "given"
    # the garment starts clear of the body's collider in the first frame's pose, as the
    # simulating stages need (ipctk's exact test; the 'clear' step, clear.py)
    from physavatar.geometry import count_intersections, submesh
    from physavatar.stages.prepare.posing import pose_body

    model, posed = pose_body(cap.body, [0], topology="collider")
    gidx, gfaces = submesh(t.faces, t.labels > 0)
    assert count_intersections(t.vertices[gidx], gfaces, posed[0], model.faces) == 0
    assert info["numbers"]["clear"]["crossing_pairs_after"] == 0 and "clear" in info["steps"]


def test_boundary_override_from_points(prepared_tiny, tiny_capture, tmp_path):
    from physavatar.stages.prepare.boundary import boundary_from_points, boundary_points

    truth = load_capture(tiny_capture).template
    pts = truth.vertices[truth.boundary]
    np.savetxt(tmp_path / "b.txt", pts)
    got = boundary_points(tmp_path / "b.txt")
    assert np.allclose(got, pts)
    t = load_capture(prepared_tiny).template
    sel = boundary_from_points(t.vertices[t.labels > 0], got, 0.05)
    assert sel.any()
    with pytest.raises(PhysavatarError, match="3D points"):
        np.savetxt(tmp_path / "bad.txt", np.zeros((3, 2)))
        boundary_points(tmp_path / "bad.txt")


# -- bad input -----------------------------------------------------------------------------------

def test_cameras_without_images_one_line(tiny_capture, tmp_path):
    src = unprepared(tiny_capture, tmp_path / "in")
    shutil.rmtree(src / "images" / "cam01")
    with pytest.raises(CaptureError) as e:
        prepare(src, out=tmp_path / "out", config=FAST, progress=False)
    assert "cam01" in str(e.value) and "\n" not in str(e.value)
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))  # nothing half written


def test_cli_prepare_bad_input_exit_2(tiny_capture, tmp_path):
    from typer.testing import CliRunner

    from physavatar.cli import app

    src = unprepared(tiny_capture, tmp_path / "in")
    (src / "cameras.json").unlink()  # a hard link to the shared capture's file: replaced, not written through
    (src / "cameras.json").write_text("[{\"name\": 1}]")
    r = CliRunner().invoke(app, ["prepare", str(src), str(tmp_path / "out")])
    assert r.exit_code == 2
    assert "cameras.json" in r.output and "Traceback" not in r.output


def test_labels_file_replaces_the_segmentation(prepared_tiny, tiny_capture, tmp_path):
    """--labels: a PLY with the true labels gives the true segmentation (up to the transfer)."""
    from physavatar.files import load_npz
    from physavatar.stages.prepare.segment import user_labels

    truth = load_capture(tiny_capture).template
    from physavatar.files import PlyMesh, write_ply

    write_ply(tmp_path / "labels.ply", PlyMesh(truth.vertices, truth.faces, {"label": truth.labels.astype(np.uint8)}))
    z = load_npz(prepared_tiny / "prepare" / "first_frame_mesh.npz")
    lab = user_labels(tmp_path / "labels.ply", z["vertices"], None)
    true = transfer_labels(z["vertices"], truth.vertices, truth.faces, truth.labels)
    assert (lab == true).all()
    with pytest.raises(PhysavatarError, match="capture's own mesh"):
        np.save(tmp_path / "l.npy", np.zeros(5, int))
        user_labels(tmp_path / "l.npy", z["vertices"], None)


def test_run_plans_prepare_first(tiny_capture, tmp_path):
    from physavatar.pipeline import needs, plan

    src = unprepared(tiny_capture, tmp_path / "in")
    steps = plan(src, tmp_path / "run")
    assert steps[0].name == "prepare" and steps[0].command[:1] == ["prepare"]
    for st in steps[1:]:
        if "capture" in st.inputs:
            assert st.inputs["capture"] == ("step", "prepare") and "prepare" in needs(st)
    assert plan(tiny_capture, tmp_path / "run2")[0].name != "prepare"


def test_imported_mesh_and_labels_are_used(prepared_tiny, tiny_capture, tmp_path):
    """A capture with its own first-frame mesh (meshes/<frame>.ply, as `physavatar import` writes
    it) carrying labels: the mesh is remeshed, not reconstructed, and its labels are kept."""
    import json

    from physavatar.files import PlyMesh, load_npz, write_ply

    z = load_npz(prepared_tiny / "prepare" / "first_frame_mesh.npz")
    src = unprepared(tiny_capture, tmp_path / "in")
    write_ply(src / "meshes" / "000000.ply",
              PlyMesh(z["vertices"], z["faces"], {"label": z["labels"].astype(np.uint8)}))
    out = prepare(src, out=tmp_path / "out", config=FAST, progress=False)
    info = json.loads((out / "prepare.json").read_text())
    assert info["steps"]["mesh"].startswith("imported (meshes/000000.ply)")
    assert info["steps"]["segmentation"] == "from the imported mesh's labels"
    got = load_npz(out / "prepare" / "first_frame_mesh.npz")
    want = transfer_labels(got["vertices"], z["vertices"], z["faces"], z["labels"])
    assert (got["labels"] == want).all()
    # remeshed to the target edge length, on the imported surface
    e = np.linalg.norm(got["vertices"][got["faces"][:, 0]] - got["vertices"][got["faces"][:, 1]], axis=1)
    assert abs(np.mean(e) / FAST.mesh.edge_length - 1) < 0.3
    assert surface_distance(got["vertices"], z["vertices"], z["faces"]).max() < 0.005
    load_capture(out)
