"""physavatar import: every format written here in its own conventions from a synthetic rig, imported back.

Cameras must come back equal to 1e-6 (in the capture's z-up world), pictures identical (PNG, or
lossless H.264 for videos), lens distortion removed so that a 3-D point lands where the new K
projects it, and bad input must give one line naming the file, exit code 2 and no OUT.
"""

from __future__ import annotations

import csv
import json
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from physavatar.camera import Camera, ring_rig
from physavatar.capture import (
    _load_cameras,
    _Problems,
    frame_name,
    read_json,
    validate_capture,
)
from physavatar.cli import app
from physavatar.errors import PhysavatarError
from physavatar.importers import ImportOptions, detect_format, import_capture
from physavatar.importers.common import rotation_to_z

runner = CliRunner()
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
Y_UP = rotation_to_z([0, 1, 0]).T  # z-up world -> y-up world (x, y, z) -> (x, z, -y)


def rig(n=3, size=(40, 30), seed=0) -> list[Camera]:
    """Cameras in the capture's z-up world with unequal focal lengths and off-centre principal points."""
    rng = np.random.default_rng(seed)
    cams = []
    for c in ring_rig(n, 2.5, 1.2, (0, 0, 0.9), size[0], size[1], 50.0):
        K = c.K.copy()
        K[0, 0] *= 1 + 0.05 * rng.random()
        K[1, 1] *= 1 + 0.05 * rng.random()
        K[:2, 2] += rng.random(2) * 2 - 1
        cams.append(Camera(c.name, c.width, c.height, K, c.w2c))
    return cams


def pictures(cams, n_frames, seed=1):
    rng = np.random.default_rng(seed)
    return {c.name: [rng.integers(0, 256, (c.height, c.width, 3), dtype=np.uint8) for _ in range(n_frames)]
            for c in cams}


def to_y_up(w2c):
    """The same camera in a world whose up axis is y (what a y-up source stores)."""
    M = np.eye(4)
    M[:3, :3] = Y_UP
    return w2c @ np.linalg.inv(M)


def load_cams(out: Path) -> dict[str, Camera]:
    return {c.name: c for c in _load_cameras(out, _Problems(strict=True))}


def assert_cameras(out: Path, cams: list[Camera], tol=1e-6):
    got = load_cams(out)
    assert sorted(got) == sorted(c.name for c in cams)
    for c in cams:
        g = got[c.name]
        assert (g.width, g.height) == (c.width, c.height)
        np.testing.assert_allclose(g.K, c.K, atol=tol)
        np.testing.assert_allclose(g.w2c, c.w2c, atol=tol)


def assert_images(out: Path, images: dict, frames: list[int], kind="images", mode="RGB"):
    for name, ims in images.items():
        for f, im in zip(frames, ims):
            got = np.asarray(Image.open(out / kind / name / f"{frame_name(f)}.png").convert(mode))
            np.testing.assert_array_equal(got, im)


def only_unprepared_problems(out: Path):
    """inspect accepts the cameras and pictures: the only problems left are what `prepare` adds."""
    rest = [str(p) for p in validate_capture(out) if not any(k in str(p) for k in ("body.npz", "template"))]
    assert rest == []


def write_video(path: Path, frames: list[np.ndarray], fps=25.0):
    import imageio_ffmpeg

    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    wr = imageio_ffmpeg.write_frames(str(path), (w, h), pix_fmt_in="rgb24", pix_fmt_out="rgb24", codec="libx264rgb",
                                     fps=fps, macro_block_size=1, quality=None,
                                     output_params=["-qp", "0", "-preset", "ultrafast", "-movflags", "+faststart"])
    wr.send(None)
    for f in frames:
        wr.send(np.ascontiguousarray(f))
    wr.close()


def save(path: Path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)


# -- ActorsHQ --------------------------------------------------------------------------------------

def write_actorshq(src: Path, cams, images, masks, frames, calib_scale=2):
    """calibration.csv (axis-angle camera->world, centre, intrinsics normalised by w, h; COLMAP's
    +0.5 pixel centres) for a full-resolution sensor ``calib_scale`` times the pictures."""
    src.mkdir(parents=True)
    with open(src / "calibration.csv", "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py"])
        for c in cams:
            r = cv2.Rodrigues(c.w2c[:3, :3].T)[0].ravel()
            W, H = c.width, c.height
            wr.writerow([c.name, W * calib_scale, H * calib_scale, *r, *c.center, c.K[0, 0] / W, c.K[1, 1] / H,
                         (c.K[0, 2] + 0.5) / W, (c.K[1, 2] + 0.5) / H])
    for c in cams:
        for f, im, m in zip(frames, images[c.name], masks[c.name]):
            save(src / "rgbs" / c.name / f"{c.name}_rgb{f:06d}.jpg", im)
            save(src / "masks" / c.name / f"{c.name}_mask{f:06d}.png", m)


def jpeg_decoded(src, cams, frames):
    return {c.name: [np.asarray(Image.open(src / "rgbs" / c.name / f"{c.name}_rgb{f:06d}.jpg").convert("RGB"))
                     for f in frames] for c in cams}


def test_actorshq_roundtrip(tmp_path):
    cams = [Camera(f"Cam{i + 1:03d}", c.width, c.height, c.K, c.w2c) for i, c in enumerate(rig())]
    frames = [0, 1, 2, 3]
    images = pictures(cams, 4)
    masks = {k: [((im[..., 0] > 128) * 255).astype(np.uint8) for im in v] for k, v in images.items()}
    src = tmp_path / "Actor01" / "Sequence1" / "4x"
    write_actorshq(src, cams, images, masks, frames)
    assert detect_format(src) == "actorshq"
    r = import_capture(src, tmp_path / "cap", options=ImportOptions(up="z"))
    assert r.frames == frames and r.fps == 25.0 and r.masks
    assert_cameras(tmp_path / "cap", cams)
    assert_images(tmp_path / "cap", jpeg_decoded(src, cams, frames), frames)
    assert_images(tmp_path / "cap", masks, frames, "masks", "L")
    only_unprepared_problems(tmp_path / "cap")
    # frame options: ids 1..3, every second -> 1, 3; half resolution scales K about pixel corners
    r = import_capture(src, tmp_path / "half", options=ImportOptions(frames="1-3", every=2, resolution="0.5", up="z"))
    assert r.frames == [1, 3]
    assert_cameras(tmp_path / "half", [c.scaled(0.5) for c in cams])
    assert read_json(tmp_path / "half" / "capture.json")["frames"] == [1, 3]
    # one calibration.csv beside the resolution folders serves them all
    (src / "calibration.csv").rename(src.parent / "calibration.csv")
    import_capture(src, tmp_path / "parent", options=ImportOptions(up="z"))
    assert_cameras(tmp_path / "parent", cams)
    run_bad([src.parent], tmp_path / "o", "rgbs", "(4x)")


# -- 4D-DRESS --------------------------------------------------------------------------------------

def test_4d_dress_roundtrip_y_up_meshes_labels(tmp_path):
    cams = [Camera(f"00{i + 4:02d}", c.width, c.height, c.K, c.w2c) for i, c in enumerate(rig())]
    frames = [11, 12, 13]
    images = pictures(cams, 3)
    masks = {k: [((im[..., 1] > 100) * 255).astype(np.uint8) for im in v] for k, v in images.items()}
    src = tmp_path / "00122" / "Inner" / "Take2"
    cap = src / "Capture"
    cap.mkdir(parents=True)
    calib = {c.name: {"intrinsics": c.K, "extrinsics": to_y_up(c.w2c)[:3]} for c in cams}
    (cap / "cameras.pkl").write_bytes(pickle.dumps(calib))
    for c in cams:
        for f, im, m in zip(frames, images[c.name], masks[c.name]):
            save(cap / c.name / "images" / f"capture-f{f:05d}.png", im)
            save(cap / c.name / "masks" / f"mask-f{f:05d}.png", m)
    rng = np.random.default_rng(3)
    V = rng.random((50, 3)) * [0.6, 0.6, 1.7]
    V[0, 2] = 0.0  # the lowest point of frame 11 is on the floor (z-up world)
    F = rng.integers(0, 50, (80, 3))
    labels = rng.integers(0, 6, 50)
    (src / "Meshes_pkl").mkdir()
    (src / "Semantic" / "labels").mkdir(parents=True)
    (src / "SMPL").mkdir()
    for f in frames:
        mesh = {"vertices": V @ Y_UP.T + [0, 0.01 * (f - 11), 0], "faces": F, "colors": rng.random((50, 3)),
                "normals": np.zeros((50, 3)), "uvs": np.zeros((50, 2)), "uv_path": "atlas.png"}
        (src / "Meshes_pkl" / f"mesh-f{f:05d}.pkl").write_bytes(pickle.dumps(mesh))
        (src / "Semantic" / "labels" / f"label-f{f:05d}.pkl").write_bytes(pickle.dumps({"scan_labels": labels}))
        (src / "SMPL" / f"mesh-f{f:05d}_smpl.pkl").write_bytes(pickle.dumps({"betas": np.zeros(10)}))
    assert detect_format(src) == "4d-dress"
    r = import_capture(src, tmp_path / "cap")  # up: auto finds y
    out = tmp_path / "cap"
    assert r.up == "y" and r.frames == frames and r.meshes == 3 and r.body_files == 3 and r.fps == 30.0
    assert_cameras(out, cams)
    assert_images(out, images, frames)
    assert_images(out, masks, frames, "masks", "L")
    from physavatar.files import read_ply

    m = read_ply(out / "meshes" / "000012.ply")
    np.testing.assert_allclose(m.vertices, V + [0, 0, 0.01], atol=1e-6)  # float32 PLY; y+ moved to z+
    np.testing.assert_array_equal(m.faces, F)
    np.testing.assert_array_equal(m.vertex_data["source_label"], labels)
    np.testing.assert_array_equal(m.vertex_data["label"], np.array([0, 0, 0, 1, 2, 3])[labels])
    assert (out / "source_body" / "smpl" / "000013.pkl").is_file()
    meta = read_json(out / "capture.json")["import"]
    np.testing.assert_allclose(np.array(meta["world_from_source"])[:3, :3], rotation_to_z([0, 1, 0]), atol=1e-12)
    only_unprepared_problems(out)


def test_pickles_cannot_run_code(tmp_path):
    src = tmp_path / "take" / "Capture"
    src.mkdir(parents=True)

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    (src / "cameras.pkl").write_bytes(pickle.dumps({"0004": Evil()}))
    with pytest.raises(PhysavatarError, match="refusing to load builtins.print"):
        import_capture(tmp_path / "take", tmp_path / "cap")


# -- EasyMocap ------------------------------------------------------------------------------------

def write_easymocap(src: Path, cams, dists=None, rot_too=True):
    src.mkdir(parents=True, exist_ok=True)
    fi = cv2.FileStorage(str(src / "intri.yml"), cv2.FILE_STORAGE_WRITE)
    fe = cv2.FileStorage(str(src / "extri.yml"), cv2.FILE_STORAGE_WRITE)
    for fs in (fi, fe):
        fs.startWriteStruct("names", cv2.FileNode_SEQ)
        for c in cams:
            fs.write("", c.name)
        fs.endWriteStruct()
    for c in cams:
        fi.write(f"K_{c.name}", c.K)
        fi.write(f"dist_{c.name}", np.zeros((1, 5)) if dists is None else dists[c.name].reshape(1, 5))
        fe.write(f"R_{c.name}", cv2.Rodrigues(c.w2c[:3, :3])[0])
        if rot_too:
            fe.write(f"Rot_{c.name}", c.w2c[:3, :3])
        fe.write(f"T_{c.name}", c.w2c[:3, 3:4])
    fi.release()
    fe.release()


def test_easymocap_images_and_videos(tmp_path):
    cams = [Camera(str(i + 1), c.width, c.height, c.K, c.w2c) for i, c in enumerate(rig())]
    images = pictures(cams, 5)
    src = tmp_path / "em"
    write_easymocap(src, cams)
    for c in cams:
        for f, im in enumerate(images[c.name]):
            save(src / "images" / c.name / f"{f:06d}.png", im)
    assert detect_format(src) == "easymocap"
    events = []
    r = import_capture(src, tmp_path / "cap", options=ImportOptions(start=0.04, end=0.12, fps=25), progress=events.append)
    assert r.frames == [1, 2, 3]
    assert [e.kind for e in events].count("advance") == 9 and events[0].total == 9 and events[-1].kind == "end"
    assert_cameras(tmp_path / "cap", cams)
    assert_images(tmp_path / "cap", {k: v[1:4] for k, v in images.items()}, [1, 2, 3])
    only_unprepared_problems(tmp_path / "cap")
    # the same rig from lossless videos: frame rate from the files, every frame decoded exactly
    vid = tmp_path / "emv"
    write_easymocap(vid, cams, rot_too=False)
    for c in cams:
        write_video(vid / "videos" / f"{c.name}.mp4", images[c.name], fps=50)
    (vid / "output" / "smpl").mkdir(parents=True)
    for f in range(5):
        (vid / "output" / "smpl" / f"{f:06d}.json").write_text(json.dumps([{"id": 0, "poses": [[0.0] * 72]}]))
    r = import_capture(vid, tmp_path / "capv")
    assert r.body_files == 5 and (tmp_path / "capv" / "source_body" / "smpl" / "000004.json").is_file()
    assert r.fps == 50 and r.frames == [0, 1, 2, 3, 4] and r.source_frames == 5
    assert_cameras(tmp_path / "capv", cams)
    assert_images(tmp_path / "capv", images, r.frames)


# -- distortion: a point drawn where the distorted lens puts it lands where the new K projects it ----

def blob_picture(cam: Camera, dist: np.ndarray, points: np.ndarray, fisheye=False) -> np.ndarray:
    rvec = cv2.Rodrigues(cam.w2c[:3, :3])[0]
    tvec = cam.w2c[:3, 3]
    if fisheye:
        uv = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), rvec, tvec, cam.K, dist[:4])[0].reshape(-1, 2)
    else:
        uv = cv2.projectPoints(points, rvec, tvec, cam.K, dist)[0].reshape(-1, 2)
    yy, xx = np.mgrid[0:cam.height, 0:cam.width]
    img = np.zeros((cam.height, cam.width))
    for u, v in uv:
        img += np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.3 ** 2))
    return np.repeat((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)[..., None], 3, axis=2)


def blob_errors(out: Path, cam: Camera, points: np.ndarray, frame=0) -> np.ndarray:
    got = load_cams(out)[cam.name]
    img = np.asarray(Image.open(out / "images" / cam.name / f"{frame_name(frame)}.png").convert("L"), np.float64)
    uv, _ = got.project(points)
    inside = (uv[:, 0] > 7) & (uv[:, 0] < cam.width - 8) & (uv[:, 1] > 7) & (uv[:, 1] < cam.height - 8)
    assert inside.sum() >= 12
    errs = []
    for u, v in uv[inside]:
        x0, y0 = int(round(u)), int(round(v))
        win = img[y0 - 5:y0 + 6, x0 - 5:x0 + 6]
        yy, xx = np.mgrid[y0 - 5:y0 + 6, x0 - 5:x0 + 6]
        cu, cv_ = (win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()
        errs.append(np.hypot(cu - u, cv_ - v))
    return np.array(errs)


def distortion_case(n=2, size=(160, 120)):
    cams = rig(n, size, seed=5)
    return cams, {c.name: cam_points(c) for c in cams}


def cam_points(c: Camera, depth=2.5) -> np.ndarray:
    """World points that the ideal lens would show on a 7x6 pixel grid covering the picture."""
    u, v = np.meshgrid(np.linspace(10, c.width - 11, 7), np.linspace(10, c.height - 11, 6))
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
    pc = pix @ np.linalg.inv(c.K).T * depth
    return pc @ c.c2w[:3, :3].T + c.c2w[:3, 3]


def check_distortion(out: Path, cams, pts, dist, frame=0):
    for c in cams:
        points = pts[c.name]
        e = blob_errors(out, c, points, frame)
        assert e.max() < 0.5, (c.name, e.max())
        # the test is not vacuous: the lens moved these points by pixels
        rvec, tvec = cv2.Rodrigues(c.w2c[:3, :3])[0], c.w2c[:3, 3]
        uv = c.project(points)[0]
        inside = (uv[:, 0] > 7) & (uv[:, 0] < c.width - 8) & (uv[:, 1] > 7) & (uv[:, 1] < c.height - 8)
        moved = np.linalg.norm(cv2.projectPoints(points, rvec, tvec, c.K, dist)[0].reshape(-1, 2) - uv, axis=1)[inside]
        assert moved.max() > 3.0


def write_pose2sim(src: Path, cams, dist, fisheye=False):
    src.mkdir(parents=True, exist_ok=True)
    lines = []
    for i, c in enumerate(cams):
        r = cv2.Rodrigues(c.w2c[:3, :3])[0].ravel()
        lines += [f"[cam_{i + 1:02d}]", f'name = "cam_{i + 1:02d}"', f"size = [ {c.width}.0, {c.height}.0]",
                  f"matrix = {json.dumps(c.K.tolist())}", f"distortions = {json.dumps(list(map(float, dist[:4])))}",
                  f"rotation = {json.dumps(r.tolist())}", f"translation = {json.dumps(c.w2c[:3, 3].tolist())}",
                  f"fisheye = {'true' if fisheye else 'false'}", ""]
    lines += ["[metadata]", "adjusted = false", "error = 0.0"]
    (src / "calibration.toml").write_text("\n".join(lines) + "\n")


def test_pose2sim_video_undistorted(tmp_path):
    cams, points = distortion_case()
    dist = np.array([-0.25, 0.08, 0.002, -0.001, 0.0])
    src = tmp_path / "p2s"
    write_pose2sim(src, cams, dist)
    named = [Camera(f"cam_{i + 1:02d}", c.width, c.height, c.K, c.w2c) for i, c in enumerate(cams)]
    for i, c in enumerate(cams):
        pic = blob_picture(c, dist, points[c.name])
        write_video(src / "videos" / f"cam{i + 1:02d}.mp4", [pic, pic[::-1].copy(), pic], fps=60)
    assert detect_format(src) == "pose2sim"
    r = import_capture(src, tmp_path / "cap")
    assert r.up == "z" and r.fps == 60 and r.frames == [0, 1, 2]
    assert_cameras(tmp_path / "cap", named)
    check_distortion(tmp_path / "cap", named, {n.name: points[c.name] for n, c in zip(named, cams)}, dist)
    only_unprepared_problems(tmp_path / "cap")


def test_nerfstudio_opengl_per_frame_intrinsics_distortion(tmp_path):
    cams, points = distortion_case(3)
    dist = np.array([-0.2, 0.05, 0.001, 0.002, 0.01])  # OpenCV order k1 k2 p1 p2 k3
    src = tmp_path / "ns"
    src.mkdir()
    c0 = cams[0]
    top = {"camera_model": "OPENCV", "fl_x": c0.K[0, 0], "fl_y": c0.K[1, 1], "cx": c0.K[0, 2] + 0.5,
           "cy": c0.K[1, 2] + 0.5, "w": c0.width, "h": c0.height, "k1": dist[0], "k2": dist[1], "k3": dist[4],
           "p1": dist[2], "p2": dist[3], "fps": 24, "frames": []}
    for t in (0.0, 0.5, 1.0):
        for j, c in enumerate(cams):
            fr = {"file_path": f"images/c{j}_t{t}.png", "time": t,
                  "transform_matrix": (c.c2w @ np.diag([1.0, -1, -1, 1])).tolist()}
            if j > 0:  # per-frame intrinsics for the other cameras
                fr.update(fl_x=c.K[0, 0], fl_y=c.K[1, 1], cx=c.K[0, 2] + 0.5, cy=c.K[1, 2] + 0.5)
            save(src / fr["file_path"], blob_picture(c, dist, points[c.name]))
            top["frames"].append(fr)
    (src / "transforms.json").write_text(json.dumps(top))
    assert detect_format(src) == "nerfstudio"
    r = import_capture(src, tmp_path / "cap", options=ImportOptions(up="z"))
    assert r.frames == [0, 1, 2] and r.fps == 24
    assert_cameras(tmp_path / "cap", cams)
    check_distortion(tmp_path / "cap", cams, points, dist, frame=2)


def test_fisheye_undistorted(tmp_path):
    cams, points = distortion_case(2)
    dist = np.array([0.1, -0.05, 0.01, 0.0])
    src = tmp_path / "fish"
    write_pose2sim(src, cams, dist, fisheye=True)
    for i, c in enumerate(cams):
        save(src / "images" / f"cam_{i + 1:02d}" / "000000.png", blob_picture(c, dist, points[c.name], fisheye=True))
    import_capture(src, tmp_path / "cap")
    for i, c in enumerate(cams):
        named = Camera(f"cam_{i + 1:02d}", c.width, c.height, c.K, c.w2c)
        assert blob_errors(tmp_path / "cap", named, points[c.name]).max() < 0.5


# -- the real Pose2Sim clip ---------------------------------------------------------------------------

def test_real_pose2sim(tmp_path):
    src = SHARED / "pose2sim"
    if not (src / "calibration.toml").is_file():
        pytest.skip("shared Pose2Sim data not present")
    r = runner.invoke(app, ["import", str(src), str(tmp_path / "cap"), "--every", "33", "--resolution", "0.25"])
    assert r.exit_code == 0, r.output
    out = tmp_path / "cap"
    meta = read_json(out / "capture.json")
    assert meta["frames"] == [0, 33, 66, 99] and meta["fps"] == 60 and meta["import"]["source_frames"] == 100
    assert meta["import"]["up"] == "z"
    cams = load_cams(out)  # strict load: rigid, finite, well-formed K
    assert sorted(cams) == ["cam_01", "cam_02", "cam_03", "cam_04"]
    # cam01 and cam02 are 1080 wide, calibrated at 1088: cropped (warned), K unchanged then scaled by 1/4
    assert "cropped" in r.output and (cams["cam_01"].width, cams["cam_03"].width) == (270, 272)
    # the cameras look at one place: the point nearest every optical axis is the person, in the
    # middle of every picture (fails for inverted extrinsics or flipped axes)
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams.values():
        P = np.eye(3) - np.outer(c.c2w[:3, 2], c.c2w[:3, 2])
        A, b = A + P, b + P @ c.center
    focus = np.linalg.solve(A, b)
    for c in cams.values():
        (u, v), z = c.project(focus[None])[0][0], c.project(focus[None])[1][0]
        assert z > 1 and abs(u / c.width - 0.5) < 0.15 and abs(v / c.height - 0.5) < 0.15, (c.name, u, v)
        assert -c.w2c[1, 2] > 0.8  # image up is world up (z): upright phones
    only_unprepared_problems(out)


# -- bad input ----------------------------------------------------------------------------------------

def run_bad(args, out: Path, *needles):
    r = runner.invoke(app, ["import", *map(str, args), str(out)])
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    line = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(line) == 1, r.output
    for n in needles:
        assert n in r.output, (n, r.output)
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if ".importing-" in p.name]
    return r.output


def small_em(tmp_path, name="em", **kw):
    cams = [Camera(str(i + 1), c.width, c.height, c.K, c.w2c) for i, c in enumerate(rig())]
    src = tmp_path / name
    write_easymocap(src, cams, **kw)
    images = pictures(cams, 3)
    for c in cams:
        for f, im in enumerate(images[c.name]):
            save(src / "images" / c.name / f"{f:06d}.png", im)
    return src, cams


def test_bad_calibration(tmp_path):
    src, cams = small_em(tmp_path)
    fe = cv2.FileStorage(str(src / "extri.yml"), cv2.FILE_STORAGE_WRITE)  # T_ of every camera missing
    fe.startWriteStruct("names", cv2.FileNode_SEQ)
    fe.write("", "1")
    fe.endWriteStruct()
    fe.write("R_1", cv2.Rodrigues(cams[0].w2c[:3, :3])[0])
    fe.release()
    run_bad([src], tmp_path / "o1", "extri.yml", "T_1")
    src, cams = small_em(tmp_path, "em2")
    fe = cv2.FileStorage(str(src / "extri.yml"), cv2.FILE_STORAGE_APPEND)
    fe.release()
    text = (src / "extri.yml").read_text()
    (src / "extri.yml").write_text(text.replace("Rot_2", "Rot_2_old").replace("Rot_3", "Rot_2", 1)
                                   .replace("Rot_2_old", "Rot_3"))  # swap two cameras' rotation matrices
    run_bad([src], tmp_path / "o2", "extri.yml", "disagree")
    (tmp_path / "nothing").mkdir()
    run_bad([tmp_path / "nothing"], tmp_path / "o3", "cannot tell the format")


def test_cameras_without_pictures_and_missing_frames(tmp_path):
    src, cams = small_em(tmp_path)
    (src / "images" / "2" / "000001.png").unlink()
    run_bad([src], tmp_path / "o1", "images/2", "lacks 1 of the 3 frames", "--truncate")
    r = import_capture(src, tmp_path / "ok", options=ImportOptions(truncate=True))
    assert r.frames == [0, 2] and r.warnings
    for p in (src / "images" / "3").iterdir():
        p.unlink()
    (src / "images" / "3").rmdir()
    run_bad([src], tmp_path / "o2", "camera '3' has neither")


def test_video_frame_counts_and_corrupt_video(tmp_path):
    cams, _ = distortion_case()
    src = tmp_path / "p2s"
    write_pose2sim(src, cams, np.zeros(5))
    pics = pictures([Camera("x", 16, 12, cams[0].K, cams[0].w2c)], 8)["x"]
    write_video(src / "videos" / "cam01.mp4", pics[:8])
    write_video(src / "videos" / "cam02.mp4", pics[:6])
    run_bad([src, "--up", "z"], tmp_path / "o1", "cam0", "frame counts differ", "--truncate")
    r = runner.invoke(app, ["import", str(src), str(tmp_path / "ok"), "--truncate", "--resolution", "160x120"])
    # the pictures are 16x12 but calibrated at 160x120: a 1/10 rescale of the calibrated picture
    assert r.exit_code == 0, r.output
    assert read_json(tmp_path / "ok" / "capture.json")["frames"] == list(range(6)) and "different" in r.output
    # truncated (moov first: the file declares 8 frames, fewer decode) and garbage
    data = (src / "videos" / "cam01.mp4").read_bytes()
    write_video(src / "videos" / "cam02.mp4", pics[:8])
    (src / "videos" / "cam01.mp4").write_bytes(data[: len(data) * 2 // 3])
    run_bad([src], tmp_path / "o2", "cam01.mp4", "truncated")
    (src / "videos" / "cam01.mp4").write_bytes(b"not a video" * 50)
    run_bad([src], tmp_path / "o3", "cam01.mp4", "cannot be opened")


def test_non_rigid_extrinsics(tmp_path):
    cams = rig(2)
    src = tmp_path / "ns"
    frames = []
    for j, c in enumerate(cams):
        c2w = c.c2w @ np.diag([1.0, -1, -1, 1])
        if j == 1:
            c2w[:3, :3] *= 1.1  # a scaled "rotation"
        frames.append({"file_path": f"{j}.png", "transform_matrix": c2w.tolist(), "fl_x": 50, "w": 40, "h": 30})
        save(src / f"{j}.png", np.zeros((30, 40, 3), np.uint8))
    (src / "transforms.json").write_text(json.dumps({"frames": frames}))
    run_bad([src], tmp_path / "o", "transforms.json", "not a rotation")


def test_options_are_checked(tmp_path):
    src, _ = small_em(tmp_path)
    run_bad([src, "--frames", "5-2"], tmp_path / "o1", "--frames")
    run_bad([src, "--resolution", "big"], tmp_path / "o2", "--resolution")
    run_bad([src, "--frames", "7-9"], tmp_path / "o3", "keep none")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    r = runner.invoke(app, ["import", str(src), str(tmp_path / "full")])
    assert r.exit_code == 2 and "not an empty folder" in r.output


# -- Anny's own pose parameters -----------------------------------------------------------------------

def test_anny_pose_parameters_become_body_npz(tmp_path):
    import torch

    from physavatar.body.model import BodyModel, BodyShape, _anny
    from physavatar.files import load_npz

    src, _ = small_em(tmp_path)
    shape = BodyShape(0.3, 0.6, 0.5, 0.4, 0.7, 0.5)
    model = _anny("tiny")
    B, T = len(model.bone_labels), 3
    rng = np.random.default_rng(7)
    D = np.tile(np.eye(4), (T, B, 1, 1))
    D[:, :, :3, :3] = np.array([[cv2.Rodrigues(rng.normal(0, 0.15, 3))[0] for _ in range(B)] for _ in range(T)])
    D[:, 0, :3, 3] = rng.normal(0, 0.3, (T, 3))
    phen = torch.as_tensor(shape.as_array()[None]).expand(T, -1)
    with torch.no_grad():  # Anny's own forward, in its default local-ref parameterization
        V_src = model(torch.as_tensor(D), phenotype_kwargs=phen, pose_parameterization="local-ref")["vertices"].numpy()
    np.savez(tmp_path / "anny.npz", pose_parameters=D, phenotype=shape.as_array(), topology="tiny",
             bone_labels=np.array(model.bone_labels))
    r = runner.invoke(app, ["import", str(src), str(tmp_path / "cap"), "--frames", "1-2", "--up", "y",
                            "--floor", "0.3", "--anny", str(tmp_path / "anny.npz")])
    assert r.exit_code == 0, r.output
    z = load_npz(tmp_path / "cap" / "body.npz")
    assert z["rotations"].shape == (2, B, 3) and str(z["topology"]) == "tiny"
    posed = BodyModel(BodyShape.from_array(z["shape"]), "tiny").pose(z["rotations"], z["root_translation"])
    expected = V_src[1:3] @ rotation_to_z([0, 1, 0]).T - [0, 0, 0.3]  # the import's placement of the source world
    np.testing.assert_allclose(posed.vertices, expected, atol=1e-6)
    # stretched bones cannot be expressed in the capture's convention
    D[:, 5, :3, 3] = 0.02
    np.savez(tmp_path / "bad.npz", pose_parameters=D, phenotype=shape.as_array(), topology="tiny")
    run_bad([src, "--anny", tmp_path / "bad.npz"], tmp_path / "o", "bad.npz", "bone heads move")


def test_nerfstudio_named_cameras_frame_keys_masks(tmp_path):
    cams = rig(2)
    images = pictures(cams, 3)
    masks = {k: [((im[..., 2] > 90) * 255).astype(np.uint8) for im in v] for k, v in images.items()}
    src = tmp_path / "ns"
    frames = []
    for f in (4, 5, 6):
        for c in cams:
            fr = {"file_path": f"rgb/{c.name}/{f}.png", "mask_path": f"mask/{c.name}/{f}.png", "camera": c.name,
                  "frame": f, "camera_model": "PINHOLE", "fl_x": c.K[0, 0], "fl_y": c.K[1, 1], "cx": c.K[0, 2] + 0.5,
                  "cy": c.K[1, 2] + 0.5, "w": c.width, "h": c.height,
                  "transform_matrix": (c.c2w @ np.diag([1.0, -1, -1, 1]))[:3].tolist()}
            save(src / fr["file_path"], images[c.name][f - 4])
            save(src / fr["mask_path"], masks[c.name][f - 4])
            frames.append(fr)
    (src / "transforms.json").write_text(json.dumps({"frames": frames}))
    r = import_capture(src / "transforms.json", tmp_path / "cap", options=ImportOptions(fps=30))
    assert r.frames == [4, 5, 6] and r.masks and r.up == "z"
    assert_cameras(tmp_path / "cap", cams)
    assert_images(tmp_path / "cap", images, [4, 5, 6])
    assert_images(tmp_path / "cap", masks, [4, 5, 6], "masks", "L")
    only_unprepared_problems(tmp_path / "cap")
