"""nerfstudio ``transforms.json``: camera → world matrices in OpenGL axes, shared or per-frame intrinsics.

Conventions (nerfstudio's data format): ``transform_matrix`` is camera → world with camera axes
x right, y up, z backwards (OpenGL), so the OpenCV camera is ``c2w · diag(1, −1, −1, 1)``;
intrinsics ``fl_x fl_y cx cy w h`` at the top level or per frame; ``camera_model`` ``OPENCV``
(``k1 k2 k3 p1 p2``: OpenCV order k1 k2 p1 p2 k3), ``OPENCV_FISHEYE`` (``k1..k4``) or ``PINHOLE``.
nerfstudio (like COLMAP) puts pixel centres at +0.5 (its rays go through ``index + 0.5``), so
the project's principal point is ``cx − 0.5``. ``file_path`` and ``mask_path`` are relative to
the file. A multi-view video lists each picture as one frame: the camera is the frame's
``camera`` / ``camera_name`` / ``camera_id`` key, or else the frames sharing one pose and
intrinsics; the frame id is its ``frame`` / ``frame_id`` / ``frame_index`` / ``timestep`` key,
or else the rank of its ``time`` among the file's distinct times, or else its order within its
camera. ``fps`` at the top level is the frame rate (else ``--fps`` or 30).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from ..files import read_json
from .common import Source, SourceCamera, View, rigid_w2c

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
CAMERA_KEYS = ("camera", "camera_name", "camera_id", "cam_id")
FRAME_KEYS = ("frame", "frame_id", "frame_index", "timestep")


def detect(src: Path) -> bool:
    return (src / "transforms.json").is_file() or (src.is_file() and src.suffix == ".json")


def _intrinsics(top: dict, fr: dict, path: Path, i: int):
    def get(k, default=None):
        return fr.get(k, top.get(k, default))

    try:
        fx = get("fl_x", get("fl_y"))
        fy = get("fl_y", fx)
        w, h = int(get("w")), int(get("h"))
        cx, cy = float(get("cx", w / 2)), float(get("cy", h / 2))
        fx, fy = float(fx), float(fy)
    except (TypeError, ValueError):
        raise PhysavatarError(path, f"frame {i}: needs fl_x (or fl_y), w and h as numbers, at the top or in the frame") from None
    model = str(get("camera_model", "OPENCV")).upper()
    k = {n: float(get(n, 0.0)) for n in ("k1", "k2", "k3", "k4", "p1", "p2")}
    if model == "OPENCV_FISHEYE":
        dist, fisheye = np.array([k["k1"], k["k2"], k["k3"], k["k4"]]), True
    elif model in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        dist, fisheye = np.array([k["k1"], k["k2"], k["p1"], k["p2"], k["k3"]]), False
        if k["k4"] != 0:
            raise PhysavatarError(path, f"frame {i}: k4 is only used by OPENCV_FISHEYE, not {model}")
    else:
        raise PhysavatarError(path, f"camera_model {model!r} is not supported (OPENCV, OPENCV_FISHEYE, PINHOLE)")
    if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
        raise PhysavatarError(path, f"frame {i}: focal lengths and sizes must be positive")
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return w, h, K, dist, fisheye


def read(src: Path) -> Source:
    path = src if src.is_file() else src / "transforms.json"
    root = path.parent
    top = read_json(path)
    frames = top.get("frames") if isinstance(top, dict) else None
    if not isinstance(frames, list) or not frames:
        raise PhysavatarError(path, "needs a non-empty list 'frames'")
    groups: dict = {}
    times = sorted({float(f["time"]) for f in frames if isinstance(f, dict) and "time" in f})
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise PhysavatarError(path, f"frame {i}: needs file_path and transform_matrix")
        try:
            c2w_gl = np.asarray(fr["transform_matrix"], np.float64)
        except (TypeError, ValueError):
            raise PhysavatarError(path, f"frame {i}: transform_matrix must be a 4x4 (or 3x4) matrix of numbers") from None
        if c2w_gl.shape not in ((3, 4), (4, 4)):
            raise PhysavatarError(path, f"frame {i}: transform_matrix must be 4x4, got {list(c2w_gl.shape)}")
        c2w = np.eye(4)
        c2w[:c2w_gl.shape[0]] = c2w_gl
        c2w = c2w @ GL_TO_CV
        Rc = c2w[:3, :3]
        w2c = rigid_w2c(Rc.T, -Rc.T @ c2w[:3, 3], path, f"frame {i}", what="transform_matrix rotation")
        w, h, K, dist, fisheye = _intrinsics(top, fr, path, i)
        key = next((str(fr[k]) for k in CAMERA_KEYS if k in fr), None)
        if key is None:
            key = tuple(np.round(np.concatenate([w2c.ravel(), K.ravel(), dist, [w, h]]), 9))
        fid = next((int(fr[k]) for k in FRAME_KEYS if k in fr), None)
        if fid is None and "time" in fr:
            fid = times.index(float(fr["time"]))
        g = groups.setdefault(key, {"cam": (w, h, K, w2c, dist, fisheye), "first": i, "images": {}, "masks": {}})
        gw, gh, gK, gw2c, gdist, _ = g["cam"]
        if np.abs(gw2c - w2c).max() > 1e-6 or np.abs(gK - K).max() > 1e-6 or (gw, gh) != (w, h) or \
                np.abs(gdist - dist).max() > 1e-9:
            raise PhysavatarError(path, f"frame {i}: camera {key!r} has another pose or intrinsics than in frame "
                                        f"{g['first']} (cameras must stay fixed over the video)")
        fid = len(g["images"]) if fid is None else fid
        if fid in g["images"]:
            raise PhysavatarError(path, f"frame {i}: camera {key!r} has two pictures for frame {fid}")
        g["images"][fid] = root / fr["file_path"]
        if "mask_path" in fr:
            g["masks"][fid] = root / fr["mask_path"]
    cams, views = [], {}
    named = all(isinstance(k, str) for k in groups)
    for j, (key, g) in enumerate(groups.items()):
        name = key if named else f"cam{j:02d}"
        w, h, K, w2c, dist, fisheye = g["cam"]
        for p in list(g["images"].values()) + list(g["masks"].values()):
            if not p.is_file():
                raise PhysavatarError(p, f"file not found (listed in {path.name} for camera {name!r})")
        cams.append(SourceCamera(name, w, h, K, w2c, dist, fisheye))
        views[name] = View(images=g["images"], masks=g["masks"] or None)
    fps = top.get("fps")
    return Source("nerfstudio", root, path, cams, views, fps=float(fps) if fps else None, default_fps=30.0)
