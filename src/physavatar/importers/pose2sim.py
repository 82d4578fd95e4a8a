"""Pose2Sim / OpenCV TOML calibration with a video (or an image folder) per camera.

Each camera is a table: ``name``, ``size`` [w, h], ``matrix`` (3x3), ``distortions``
(k1 k2 p1 p2), ``rotation`` (Rodrigues, world → camera), ``translation`` (metres), ``fisheye``;
other tables (``[metadata]``) are skipped. Read with ``tomllib`` (the standard library).
Pictures: ``videos/`` (or ``--videos DIR``) holds one video per camera, matched by name with
separators and case ignored (``cam_01`` ↔ ``cam01.mp4``); an image folder per camera
(``images/<cam>/``) works too. Pose2Sim calibrates with Z up, so ``--up auto`` finds z.
"""

from __future__ import annotations

import re
import tomllib
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


def _tomls(src: Path) -> list[Path]:
    if src.is_file() and src.suffix == ".toml":
        return [src]
    return sorted(src.glob("*.toml")) or sorted((src / "calibration").glob("*.toml"))


def detect(src: Path) -> bool:
    return bool(_tomls(src))


def _key(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


def _videos(folder: Path) -> dict[str, Path]:
    return {_key(p.stem): p for p in sorted(folder.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES} \
        if folder.is_dir() else {}


def read(src: Path, options: ImportOptions) -> Source:
    tomls = _tomls(src)
    if not tomls:
        raise PhysavatarError(src, "no calibration .toml here or in calibration/")
    if len(tomls) > 1:
        raise PhysavatarError(src, f"several .toml calibrations ({', '.join(p.name for p in tomls)}); pass the one to use as SRC")
    path = tomls[0]
    root = src if src.is_dir() else src.parent
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise PhysavatarError(path, f"not valid TOML ({e})") from None
    vdir = options.videos if options.videos is not None else root / "videos"
    vdir = vdir if vdir.is_absolute() else root / vdir
    videos = _videos(vdir)
    cams, views = [], {}
    for section, c in data.items():
        if not isinstance(c, dict) or section == "metadata":
            continue
        name = str(c.get("name", section))
        missing = [k for k in ("size", "matrix", "rotation", "translation") if k not in c]
        if missing:
            raise PhysavatarError(path, f"camera {name!r}: missing {missing}")
        try:
            w, h = (int(round(float(x))) for x in c["size"])
            K = check_K(c["matrix"], path, name)
            R = rodrigues(np.asarray(c["rotation"], np.float64).reshape(3))
            T = np.asarray(c["translation"], np.float64).reshape(3)
            dist = np.asarray(c.get("distortions", [0, 0, 0, 0]), np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise PhysavatarError(path, f"camera {name!r}: size [w, h], a 3x3 matrix and 3-value rotation and "
                                        "translation are needed") from None
        fisheye = bool(c.get("fisheye", False))
        if dist.size not in (4, 5, 8) or not np.isfinite(dist).all():
            raise PhysavatarError(path, f"camera {name!r}: distortions must be 4, 5 or 8 finite values")
        cams.append(SourceCamera(name, w, h, K, rigid_w2c(R, T, path, name), dist, fisheye))
        images = numbered_files(root / "images" / name)
        video = videos.get(_key(name))
        if images:
            views[name] = View(images=images)
        elif video is not None:
            views[name] = View(video=video)
        else:
            raise PhysavatarError(vdir, f"no video for camera {name!r} (looked for {name}.mp4 and other video files "
                                        "named like the camera)")
    if not cams:
        raise PhysavatarError(path, "no camera tables")
    return Source("pose2sim", root, path, cams, views, fps=None, default_fps=30.0)
