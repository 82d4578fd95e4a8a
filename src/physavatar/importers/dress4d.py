"""4D-DRESS: ``Capture/cameras.pkl``, per-camera images and masks, meshes and garment labels.

Layout of one take (SRC; ``SRC/Capture`` is accepted too)::

    Capture/cameras.pkl                        {cam: {"intrinsics": 3x3, "extrinsics": 3x4 world→camera}}
    Capture/<cam>/images/capture-fNNNNN.png
    Capture/<cam>/masks/mask-fNNNNN.png
    Meshes_pkl/mesh-fNNNNN.pkl                 {"vertices", "faces", "colors", ...}
    Semantic/labels/label-fNNNNN.pkl           {"scan_labels": [V]} 0 skin 1 hair 2 shoe 3 upper 4 lower 5 outer
    SMPL/mesh-fNNNNN_smpl.pkl, SMPLX/mesh-fNNNNN_smplx.pkl   body-model fits (copied as they are)

Cameras are OpenCV (x right, y down, z forward, pixel centres at integers); the calibration has
no image size, so it is the first image's. The per-vertex labels become the capture's label
convention in the imported meshes: skin, hair and shoes are body (0), upper 1, lower 2, outer 3;
the source's label is kept as ``source_label``. Frame rate: 30 fps unless ``--fps``.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .common import Source, SourceCamera, View, check_K, numbered_files, rigid_w2c
from .media import image_size
from .meshes import load_pickle

FPS = 30.0
SURFACE_LABELS = ["skin", "hair", "shoe", "upper", "lower", "outer"]
TO_CAPTURE_LABEL = np.array([0, 0, 0, 1, 2, 3], np.uint8)


def _root(src: Path) -> Path:
    return src.parent if src.name == "Capture" and (src / "cameras.pkl").is_file() else src


def detect(src: Path) -> bool:
    return (_root(src) / "Capture" / "cameras.pkl").is_file()


def _mesh(mesh_path: Path, label_path: Path | None):
    d = load_pickle(mesh_path)
    try:
        v = np.asarray(d["vertices"], np.float64).reshape(-1, 3)
        f = np.asarray(d["faces"], np.int64).reshape(-1, 3)
    except (KeyError, TypeError, ValueError):
        raise PhysavatarError(mesh_path, "needs 'vertices' [V, 3] and 'faces' [F, 3]") from None
    data = {}
    c = d.get("colors") if isinstance(d, dict) else None
    if c is not None:
        c = np.asarray(c)
        if c.ndim == 2 and c.shape[0] == len(v) and c.shape[1] >= 3:
            c = c[:, :3]
            c = np.clip(c * 255.0 + 0.5, 0, 255) if c.dtype.kind == "f" and c.max() <= 1.0 else c
            data.update(red=c[:, 0].astype(np.uint8), green=c[:, 1].astype(np.uint8), blue=c[:, 2].astype(np.uint8))
    if label_path is not None:
        lab = load_pickle(label_path)
        s = np.asarray(lab.get("scan_labels") if isinstance(lab, dict) else lab).reshape(-1)
        if s.shape != (len(v),) or s.min() < 0 or s.max() >= len(SURFACE_LABELS):
            raise PhysavatarError(label_path, f"'scan_labels' must be {len(v)} values in 0..{len(SURFACE_LABELS) - 1} "
                                              f"({', '.join(SURFACE_LABELS)})")
        s = s.astype(np.int64)
        data.update(label=TO_CAPTURE_LABEL[s], source_label=s.astype(np.uint8))
    return v, f, data


def read(src: Path) -> Source:
    root = _root(src)
    path = root / "Capture" / "cameras.pkl"
    raw = load_pickle(path)
    if not isinstance(raw, dict) or not raw:
        raise PhysavatarError(path, "must be a dict {camera: {intrinsics, extrinsics}} with at least one camera")
    cams, views = [], {}
    for name in sorted(raw, key=str):
        c = raw[name]
        name = str(name)
        if not isinstance(c, dict) or "intrinsics" not in c or "extrinsics" not in c:
            raise PhysavatarError(path, f"camera {name!r}: needs 'intrinsics' (3x3) and 'extrinsics' (3x4 world→camera)")
        K = check_K(c["intrinsics"], path, name)
        E = np.asarray(c["extrinsics"], np.float64)
        if E.shape not in ((3, 4), (4, 4)):
            raise PhysavatarError(path, f"camera {name!r}: extrinsics must be 3x4, got {list(E.shape)}")
        w2c = rigid_w2c(E[:3, :3], E[:3, 3], path, name)
        folder = root / "Capture" / name
        images = numbered_files(folder / "images", pattern=r"capture-f(\d+)\.\w+")
        if not images:
            raise PhysavatarError(folder / "images", f"camera {name!r} has no images (capture-fNNNNN.png)")
        w, h = image_size(images[min(images)])
        masks = numbered_files(folder / "masks", pattern=r"mask-f(\d+)\.\w+")
        cams.append(SourceCamera(name, w, h, K, w2c))
        views[name] = View(images=images, masks=masks or None)
    labels = numbered_files(root / "Semantic" / "labels", (".pkl",), r"label-f(\d+)\.pkl")
    meshes = {f: partial(_mesh, p, labels.get(f))
              for f, p in numbered_files(root / "Meshes_pkl", (".pkl",), r"mesh-f(\d+)\.pkl").items()}
    body = {kind: numbered_files(root / folder, (".pkl",), rf"mesh-f(\d+)_{kind}\.pkl")
            for kind, folder in (("smpl", "SMPL"), ("smplx", "SMPLX"))}
    body = {k: v for k, v in body.items() if v}
    notes = {"labels": "label: 0 body (skin, hair, shoe), 1 upper, 2 lower, 3 outer; source_label: 4D-DRESS scan_labels"} \
        if labels else {}
    return Source("4d-dress", root, path, cams, views, fps=FPS, meshes=meshes, body_files=body, notes=notes)
