"""EasyMocap: ``intri.yml`` / ``extri.yml`` (OpenCV FileStorage) with images or videos per camera.

``intri.yml``: ``names`` (the camera list), ``K_<cam>`` (3x3), ``dist_<cam>`` (1x5: k1 k2 p1 p2 k3).
``extri.yml``: ``R_<cam>`` (Rodrigues 3x1) and/or ``Rot_<cam>`` (3x3), ``T_<cam>`` (3x1):
world → camera, OpenCV axes, pixel centres at integers. When both ``R_`` and ``Rot_`` are given
they must agree. Pictures: ``images/<cam>/NNNNNN.jpg`` (frame id from the name) or
``videos/<cam>.mp4`` (frame id = index); masks from ``mask/<cam>/`` or ``masks/<cam>/`` when
present; EasyMocap's body fits (``output/smpl/NNNNNN.json``, ``smplx`` ...) are copied to
``source_body/``. Read with ``cv2.FileStorage``, the library that writes these files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .common import (
    VIDEO_SUFFIXES,
    ImportOptions,
    Source,
    SourceCamera,
    View,
    check_K,
    numbered_files,
    rigid_w2c,
    rodrigues,
)
from .media import image_size, video_info


def detect(src: Path) -> bool:
    return (src / "intri.yml").is_file() and (src / "extri.yml").is_file()


class _Storage:
    def __init__(self, path: Path):
        import cv2

        self.path = path
        if not path.is_file():
            raise PhysavatarError(path, "file not found")
        try:
            self.fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
            ok = self.fs.isOpened()
        except cv2.error as e:
            raise PhysavatarError(path, f"not a readable OpenCV FileStorage YAML file ({str(e).strip().splitlines()[-1]})") from None
        if not ok:
            raise PhysavatarError(path, "not a readable OpenCV FileStorage YAML file")

    def mat(self, key: str) -> np.ndarray | None:
        node = self.fs.getNode(key)
        if node.empty() or node.isNone():
            return None
        m = node.mat()
        if m is None:
            raise PhysavatarError(self.path, f"{key} is not an OpenCV matrix (!!opencv-matrix)")
        return np.asarray(m, np.float64)

    def names(self) -> list[str]:
        node = self.fs.getNode("names")
        if node.empty() or not node.isSeq():
            raise PhysavatarError(self.path, "missing the list 'names' of cameras")
        return [node.at(i).string() if node.at(i).isString() else str(int(node.at(i).real())) for i in range(node.size())]


def _pictures(src: Path, name: str, options: ImportOptions) -> tuple[View, tuple[int, int]]:
    images = numbered_files(src / "images" / name)
    masks = numbered_files(src / "mask" / name) or numbered_files(src / "masks" / name)
    if images:
        return View(images=images, masks=masks or None), image_size(images[min(images)])
    vdir = options.videos if options.videos is not None else src / "videos"
    vdir = vdir if vdir.is_absolute() else src / vdir
    for suffix in VIDEO_SUFFIXES:
        p = vdir / f"{name}{suffix}"
        if p.is_file():
            i = video_info(p)
            return View(video=p, masks=masks or None), (i.width, i.height)
    raise PhysavatarError(src, f"camera {name!r} has neither images/{name}/NNNNNN.jpg nor videos/{name}.mp4")


def read(src: Path, options: ImportOptions) -> Source:
    intri = _Storage(src / "intri.yml")
    extri = _Storage(src / "extri.yml")
    names = intri.names()
    if not names:
        raise PhysavatarError(intri.path, "'names' is empty")
    cams, views = [], {}
    for name in names:
        K = intri.mat(f"K_{name}")
        if K is None:
            raise PhysavatarError(intri.path, f"camera {name!r}: missing K_{name}")
        K = check_K(K, intri.path, name)
        dist = intri.mat(f"dist_{name}")
        dist = None if dist is None or dist.size == 0 else dist.reshape(-1)
        if dist is not None and (dist.size not in (4, 5, 8) or not np.isfinite(dist).all()):
            raise PhysavatarError(intri.path, f"camera {name!r}: dist_{name} must be 4, 5 or 8 finite values, got {dist.size}")
        rvec, Rot, T = extri.mat(f"R_{name}"), extri.mat(f"Rot_{name}"), extri.mat(f"T_{name}")
        if T is None or (rvec is None and Rot is None):
            raise PhysavatarError(extri.path, f"camera {name!r}: needs T_{name} and R_{name} (Rodrigues) or Rot_{name}")
        if rvec is not None and rvec.size != 3:
            raise PhysavatarError(extri.path, f"camera {name!r}: R_{name} must be a Rodrigues vector of 3 values, got {rvec.size}")
        R = Rot if Rot is not None else rodrigues(rvec)
        w2c = rigid_w2c(R, T, extri.path, name, what=f"Rot_{name}" if Rot is not None else f"R_{name}")
        if Rot is not None and rvec is not None and np.abs(rodrigues(rvec) - Rot).max() > 1e-5:
            raise PhysavatarError(extri.path, f"camera {name!r}: R_{name} and Rot_{name} disagree "
                                              f"(by {np.abs(rodrigues(rvec) - Rot).max():.3g}): inconsistent calibration")
        view, (w, h) = _pictures(src, name, options)
        cams.append(SourceCamera(name, w, h, K, w2c, dist))
        views[name] = view
    body = {}
    for kind in ("smpl", "smplx", "smplh", "manol"):  # EasyMocap's fits, output/<model>/NNNNNN.json
        files = numbered_files(src / "output" / kind, (".json",)) or numbered_files(src / kind, (".json",))
        if files:
            body[kind] = files
    return Source("easymocap", src, extri.path, cams, views, fps=None, default_fps=30.0, body_files=body)
