"""ActorsHQ (HumanRF): ``calibration.csv``, ``rgbs/CamNNN/CamNNN_rgbFFFFFF.jpg``, ``masks/...``.

``calibration.csv`` has the header ``name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py``: ``r`` the
axis-angle rotation camera → world, ``t`` the camera centre in metres, ``fx, fy, px, py``
normalised by ``w`` and ``h``. Cameras are right-down-forward (OpenCV axes). HumanRF's own
COLMAP export copies ``px·w`` unchanged into COLMAP, whose pixel centres sit at +0.5, so the
principal point in the project's convention (centres at integers) is ``px·w − 0.5``; because
the intrinsics are normalised, pictures of a downscaled folder (``4x/``) get ``px·W − 0.5`` for
their own width W. Per-frame meshes, when present, are ``meshes/*.obj|ply`` with the frame id
as the last number of the name (ActorsHQ's Alembic meshes extracted per frame, e.g.
``FrameRec000460.obj``). Frame rate: 25 fps unless ``--fps``.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .common import Source, SourceCamera, View, numbered_files, rodrigues
from .meshes import mesh_files

FPS = 25.0
COLUMNS = ["name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py"]


def detect(src: Path) -> bool:
    return (src / "calibration.csv").is_file() or ((src / "rgbs").is_dir() and (src.parent / "calibration.csv").is_file())


def read(src: Path) -> Source:
    path = src / "calibration.csv"
    if not path.is_file() and (src.parent / "calibration.csv").is_file():
        path = src.parent / "calibration.csv"  # one calibration for every resolution folder (normalised intrinsics)
    if not path.is_file():
        raise PhysavatarError(path, "file not found (an ActorsHQ folder holds calibration.csv, rgbs/ and masks/)")
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
            header = rows and list(rows[0].keys())
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise PhysavatarError(path, f"not a readable CSV file ({e})") from None
    if not rows:
        raise PhysavatarError(path, "no cameras (expected the header " + ",".join(COLUMNS) + " and one row per camera)")
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise PhysavatarError(path, f"missing columns {missing} (expected {','.join(COLUMNS)})")
    if not (src / "rgbs").is_dir():
        scales = sorted(p.name for p in src.iterdir() if (p / "rgbs").is_dir())
        hint = f"; pass one of the resolution folders as SRC ({', '.join(scales)})" if scales else ""
        raise PhysavatarError(src / "rgbs", f"folder not found (ActorsHQ pictures: rgbs/CamNNN/CamNNN_rgbFFFFFF.jpg){hint}")
    cams, views = [], {}
    for i, row in enumerate(rows):
        try:
            name = row["name"].strip()
            w, h = int(float(row["w"])), int(float(row["h"]))
            r = np.array([float(row[k]) for k in ("rx", "ry", "rz")])
            C = np.array([float(row[k]) for k in ("tx", "ty", "tz")])
            fx, fy, px, py = (float(row[k]) for k in ("fx", "fy", "px", "py"))
        except (TypeError, ValueError, AttributeError):
            raise PhysavatarError(path, f"row {i + 2}: values must be numbers") from None
        if not np.isfinite([*r, *C, fx, fy, px, py]).all() or fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
            raise PhysavatarError(path, f"camera {name!r}: sizes and focal lengths must be positive and finite")
        R_c2w = rodrigues(r)
        w2c = np.eye(4)
        w2c[:3, :3] = R_c2w.T
        w2c[:3, 3] = -R_c2w.T @ C
        K = np.array([[fx * w, 0.0, px * w - 0.5], [0.0, fy * h, py * h - 0.5], [0.0, 0.0, 1.0]])
        cams.append(SourceCamera(name, w, h, K, w2c))
        images = numbered_files(src / "rgbs" / name, pattern=rf"{name}_rgb(\d+)\.\w+")
        masks = numbered_files(src / "masks" / name, pattern=rf"{name}_mask(\d+)\.\w+")
        views[name] = View(images=images, masks=masks or None)
        if not images:
            raise PhysavatarError(src / "rgbs" / name, f"camera {name!r} has no images ({name}_rgbNNNNNN.jpg)")
    meshes = mesh_files(src / "meshes")
    return Source("actorshq", src, path, cams, views, fps=FPS, meshes=meshes)
