"""What every importer shares: the source description a format module returns, the import options,
frame selection, rigidity checks and where the world is placed.

A format module (``actorshq.py``, ``dress4d.py``, ``easymocap.py``, ``pose2sim.py``,
``nerfstudio.py``) only reads its own files into a :class:`Source`: cameras in the OpenCV
convention (x right, y down, z forward, ``K`` in pixels with pixel centres at integer coordinates,
``w2c`` world → camera) with their lens distortion, and per camera either image files by frame id
or one video. :mod:`physavatar.importers.write` turns a ``Source`` into a capture folder.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..capture import rigid_problem
from ..errors import PhysavatarError

log = logging.getLogger("physavatar.importers")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")


@dataclass
class SourceCamera:
    """One calibrated view as the source describes it, already in the OpenCV convention.

    Attributes:
        name: camera name (the folder under ``images/`` in the capture).
        width, height: image size the calibration is for.
        K: [3, 3] pixels, pixel centres at integer coordinates.
        w2c: [4, 4] rigid world → camera (the source's world and units).
        dist: OpenCV distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]; fisheye: k1..k4)
            or None.
        fisheye: the Kannala–Brandt model of ``cv2.fisheye`` instead of OpenCV's radial-tangential.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    w2c: np.ndarray
    dist: np.ndarray | None = None
    fisheye: bool = False

    @property
    def distorted(self) -> bool:
        return self.dist is not None and bool(np.any(np.asarray(self.dist) != 0))


@dataclass
class View:
    """One camera's pictures: image files by frame id, or one video (frame id = index from 0)."""

    images: dict[int, Path] | None = None
    video: Path | None = None
    masks: dict[int, Path] | None = None


MeshLoader = Callable[[], tuple[np.ndarray, np.ndarray, dict]]  # -> vertices [V,3], faces [F,3], per-vertex arrays


@dataclass
class Source:
    """Everything an importer read, before frame selection and placement.

    ``meshes``: per frame id, a function returning the source's mesh (vertices in the source's
    world, faces, per-vertex arrays such as ``red/green/blue`` or ``label``). ``body_files``: the
    source's body-model parameter files by kind (``smpl``, ``smplx``) and frame id, copied as they
    are. ``fps``: None when the videos say it (or unknown: ``default_fps``).
    """

    format: str
    root: Path
    calibration: Path
    cameras: list[SourceCamera]
    views: dict[str, View]
    fps: float | None = None
    default_fps: float = 30.0
    meshes: dict[int, MeshLoader] = field(default_factory=dict)
    body_files: dict[str, dict[int, Path]] = field(default_factory=dict)
    notes: dict = field(default_factory=dict)


@dataclass
class ImportOptions:
    """What to take from the source and how to place it (``physavatar import`` options).

    frames: frame ids to keep, e.g. ``"0-99"`` or ``"0,5,10-20"`` (source frame ids; video frames
        count from 0). every: keep every n-th of the selected frames. start, end: a time range in
        seconds from the first frame. resolution: ``"0.5"`` (a factor) or ``"540x960"`` (pixels).
        fps: override the source's frame rate. truncate: cut every camera to the frames all of
        them have (a warning) instead of stopping with an error. up: the source's up axis
        (``auto``: from the cameras' image-up directions; ``x``, ``y``, ``z``, ``-x`` ...).
        scale: metres per source unit. floor: ``auto`` (the lowest vertex of the first kept
        frame's mesh goes to z = 0 when the source has meshes; otherwise the origin is kept),
        ``keep``, or a height (after rotation and scaling) moved to z = 0. videos: a folder of
        videos to use instead of the format's default one. anny: an ``.npz`` of Anny's own pose
        parameters in the source's world, converted to ``body.npz`` (importers/anny.py).
    """

    frames: str | None = None
    every: int = 1
    start: float | None = None
    end: float | None = None
    resolution: str | None = None
    fps: float | None = None
    truncate: bool = False
    up: str = "auto"
    scale: float = 1.0
    floor: str = "auto"
    videos: Path | None = None
    anny: Path | None = None

    def check(self) -> None:
        if self.every < 1:
            raise PhysavatarError(None, f"option --every: must be at least 1, got {self.every}")
        if self.scale <= 0 or not np.isfinite(self.scale):
            raise PhysavatarError(None, f"option --scale: must be positive, got {self.scale}")
        if self.fps is not None and not self.fps > 0:
            raise PhysavatarError(None, f"option --fps: must be positive, got {self.fps}")
        if self.start is not None and self.end is not None and self.end < self.start:
            raise PhysavatarError(None, f"option --end: {self.end} is before --start {self.start}")
        if self.up not in ("auto",) + tuple(AXES):
            raise PhysavatarError(None, f"option --up: {self.up!r} is not auto, {', '.join(AXES)}")
        if self.floor not in ("auto", "keep"):
            try:
                float(self.floor)
            except ValueError:
                raise PhysavatarError(None, f"option --floor: {self.floor!r} is not auto, keep or a number") from None
        parse_frames(self.frames)
        parse_resolution(self.resolution)
        if self.anny is not None and not Path(self.anny).is_file():
            raise PhysavatarError(self.anny, "Anny pose file not found (option --anny)")


# -- option parsing ------------------------------------------------------------------------------

def parse_frames(text: str | None) -> list[tuple[int, int]] | None:
    """``"0-9,20,30-40"`` -> inclusive ranges [(0, 9), (20, 20), (30, 40)]; None keeps every frame."""
    if text is None or not str(text).strip():
        return None
    out = []
    for part in str(text).split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if not m:
            raise PhysavatarError(None, f"option --frames: {part.strip()!r} is not a frame id or a range a-b")
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) is not None else a
        if b < a:
            raise PhysavatarError(None, f"option --frames: range {a}-{b} is empty")
        out.append((a, b))
    return out


def parse_resolution(text: str | None) -> float | tuple[int, int] | None:
    """``"0.5"`` -> 0.5 (a factor); ``"540x960"`` -> (540, 960) (width, height); None: keep."""
    if text is None or not str(text).strip():
        return None
    s = str(text).strip().lower()
    m = re.fullmatch(r"(\d+)\s*x\s*(\d+)", s)
    if m:
        w, h = int(m.group(1)), int(m.group(2))
        if w < 1 or h < 1:
            raise PhysavatarError(None, f"option --resolution: {text!r} must be positive")
        return w, h
    try:
        f = float(s)
    except ValueError:
        raise PhysavatarError(None, f"option --resolution: {text!r} is neither a factor (0.5) nor WxH (540x960)") from None
    if not (0 < f <= 8):
        raise PhysavatarError(None, f"option --resolution: factor {f} must be in (0, 8]")
    return f


class FrameFilter:
    """Decides, frame id by frame id in increasing order, whether a frame is kept.

    Stateful only through the first kept id (``every`` counts from it), so the decision for a
    frame does not depend on how many frames follow: a video's frames can be filtered while
    they are decoded, before its length is known.
    """

    def __init__(self, options: ImportOptions, fps: float, first_id: int):
        self.ranges = parse_frames(options.frames)
        self.every = options.every
        self.start, self.end = options.start, options.end
        self.fps, self.first_id = fps, first_id
        self.anchor: int | None = None
        self.count = 0

    def __call__(self, f: int) -> bool:
        if self.ranges is not None and not any(a <= f <= b for a, b in self.ranges):
            return False
        t = (f - self.first_id) / self.fps
        if self.start is not None and t < self.start - 1e-9:
            return False
        if self.end is not None and t > self.end + 1e-9:
            return False
        self.count += 1
        return (self.count - 1) % self.every == 0


def select_frames(ids, options: ImportOptions, fps: float) -> list[int]:
    ids = sorted(int(i) for i in ids)
    if not ids:
        return []
    keep = FrameFilter(options, fps, ids[0])
    return [f for f in ids if keep(f)]


# -- geometry checks -----------------------------------------------------------------------------

def rigid_w2c(R, t, where: Path, camera: str, what: str = "rotation") -> np.ndarray:
    """[4, 4] from a 3x3 ``R`` and a 3-vector ``t``; PhysavatarError when R is not a rotation."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,):
        raise PhysavatarError(where, f"camera {camera!r}: {what} must be 3x3 and translation 3 values, "
                                     f"got {list(R.shape)} and {list(t.shape)}")
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = t
    problem = rigid_problem(w2c)  # the capture's own check: finite, R a rotation
    if problem:
        raise PhysavatarError(where, f"camera {camera!r} ({what}): {problem}: extrinsics must be rigid")
    return w2c


def rodrigues(rvec) -> np.ndarray:
    """[3] axis-angle -> [3, 3] rotation (OpenCV's Rodrigues formula)."""
    import cv2

    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return R


def check_K(K, where: Path, camera: str) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise PhysavatarError(where, f"camera {camera!r}: intrinsics must be a finite 3x3 matrix, got shape {list(K.shape)}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
        raise PhysavatarError(where, f"camera {camera!r}: intrinsics need positive focal lengths and last row [0, 0, 1]")
    return K


def frame_number(name: str) -> int | None:
    """The frame id in a file name: the last group of digits (``Cam001_rgb000460.jpg`` -> 460)."""
    m = re.findall(r"(\d+)", Path(name).stem)
    return int(m[-1]) if m else None


def numbered_files(folder: Path, suffixes=IMAGE_SUFFIXES, pattern: str | None = None) -> dict[int, Path]:
    """Files of ``folder`` by the frame number in their names (``pattern``: a regex with one group)."""
    out: dict[int, Path] = {}
    if not folder.is_dir():
        return out
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in suffixes or p.name.startswith("."):
            continue
        if pattern is not None:
            m = re.fullmatch(pattern, p.name)
            if not m:
                continue
            f = int(m.group(1))
        else:
            f = frame_number(p.name)
            if f is None:
                continue
        if f in out:
            raise PhysavatarError(folder, f"two files for frame {f}: {out[f].name} and {p.name}")
        out[f] = p
    return out


# -- world placement -----------------------------------------------------------------------------

AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1), "-x": (-1, 0, 0), "-y": (0, -1, 0), "-z": (0, 0, -1)}


def rotation_to_z(up) -> np.ndarray:
    """[3, 3] the smallest rotation taking the unit vector ``up`` to +z."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])  # half turn about x
    v = np.cross(u, z)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def estimate_up(cameras: list[SourceCamera], where: Path) -> str:
    """The signed world axis the cameras' image-up directions agree on.

    Rig cameras stand upright: the world direction of a camera's image up, −(row 1 of R), points
    up. Their mean, snapped to the nearest signed axis, is the up axis; when the mean is shorter
    than 0.5 or more than 30° from every axis, the cameras cannot tell and the user must say.
    """
    ups = np.array([-c.w2c[1, :3] for c in cameras])
    m = ups.mean(0)
    n = np.linalg.norm(m)
    best = max(AXES, key=lambda a: float(np.dot(m, AXES[a])))
    if n < 0.5 or np.dot(m / max(n, 1e-12), AXES[best]) < np.cos(np.radians(30)):
        raise PhysavatarError(where, "cannot tell the world's up axis from the cameras (they do not stand upright "
                                     "together); pass --up x|y|z|-x|-y|-z")
    return best


@dataclass
class Placement:
    """world' = scale · R · world + offset (z up, metres): ``matrix`` [4, 4] is that similarity."""

    up: str
    scale: float
    R: np.ndarray
    offset: np.ndarray

    @property
    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = self.offset
        return M

    def points(self, p: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(p, np.float64) @ self.R.T + self.offset

    def w2c(self, w2c: np.ndarray) -> np.ndarray:
        """The same camera in the placed world: R' = R Aᵀ, centre C' = s A C + o (pixels unchanged)."""
        Rc, t = w2c[:3, :3], w2c[:3, 3]
        C = -Rc.T @ t
        R2 = Rc @ self.R.T
        C2 = self.points(C[None])[0]
        out = np.eye(4)
        out[:3, :3] = R2
        out[:3, 3] = -R2 @ C2
        return out
