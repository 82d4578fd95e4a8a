"""The body fit's observations (:mod:`.body_fit`): the capture's cameras, frames and masks (at the
working resolution), the detector's keypoints checked against the other views, and where the
body stands in the masks' visual hull (placement of the first frame)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from ...body.fit_terms import MaskView
from ...camera import Camera
from ...errors import PhysavatarError
from ...files import read_json
from .keypoints import detect_capture, make_detector, triangulate

# -- reading the capture -------------------------------------------------------------------------

def _read_capture(root: Path) -> tuple[list[Camera], list[int]]:
    meta = read_json(root / "capture.json")
    try:
        frames = [int(f) for f in meta["frames"]]
        cams = [Camera.from_dict(d) for d in read_json(root / "cameras.json")]
    except (KeyError, TypeError, ValueError) as e:
        raise PhysavatarError(root, f"capture.json or cameras.json is malformed ({e})") from None
    if not frames or not cams:
        raise PhysavatarError(root, "the capture lists no frames or no cameras")
    return cams, frames


def _read_mask(path: Path, size: tuple[int, int]) -> np.ndarray:
    try:
        with Image.open(path) as im:
            im = im.convert("L")
            if im.size != size:
                im = im.resize(size, Image.BILINEAR)
            return np.asarray(im, dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise PhysavatarError(path, "mask not found (the body fit needs a mask for every camera and frame)") from None
    except Exception as e:  # noqa: BLE001
        raise PhysavatarError(path, f"unreadable or corrupt mask ({type(e).__name__})") from None


class _Observations:
    """Masks (at the working resolution), keypoints and the clothed mesh of a capture."""

    def __init__(self, root: Path, cfg, progress):
        self.root = root
        cams, self.frames = _read_capture(root)
        self.native = cams
        self.cams = [c.scaled(min(1.0, cfg.max_resolution / max(c.width, c.height))) for c in cams]
        self.rng = np.random.default_rng(cfg.seed)
        self.cfg = cfg
        self._views: dict[int, list[MaskView]] = {}
        if not (root / "masks").is_dir():
            raise PhysavatarError(root / "masks", "no masks: the body fit needs the masks of every view")
        try:
            self.detector, self.detector_note = make_detector(cfg.keypoints)
        except ImportError as e:
            raise PhysavatarError(None, f"option --keypoints mediapipe: {e}") from None
        self.kp = None  # [T, C, K, 2] px at the working resolution, conf [T, C, K]
        if self.detector is not None:
            self._detect(progress)

    def views(self, t: int) -> list[MaskView]:
        if t not in self._views:
            f = f"{self.frames[t]:06d}.png"
            self._views[t] = [MaskView.build(c, _read_mask(self.root / "masks" / n.name / f, (c.width, c.height)),
                                             self.cfg.max_contour, self.rng) for c, n in zip(self.cams, self.native)]
        return self._views[t]

    def _detect(self, progress) -> None:
        T, C = len(self.frames), len(self.cams)
        # the keypoints prepare detected already (prepare/keypoints.npz, for the cameras' check)
        saved = self.root / "prepare" / "keypoints.npz"
        z = np.load(saved) if saved.is_file() else None
        if z is not None and z["keypoints"].shape == (T, C, 33, 2) and list(z["frames"]) == list(self.frames):
            native, conf = z["keypoints"], z["confidence"].copy()
        else:
            native, conf = detect_capture(self.root, self.native, self.frames, self.detector, progress)
        kp = np.zeros((T, C, 33, 2))
        for c, (cam, nat) in enumerate(zip(self.cams, self.native)):
            s = cam.width / nat.width
            kp[:, c] = (native[:, c] + 0.5) * s - 0.5
        # drop detections that disagree with the other views (RANSAC triangulation)
        thr = np.array([0.04 * max(c.width, c.height) for c in self.cams])
        self.tri = []
        for t in range(T):
            tri = triangulate(kp[t], conf[t], self.cams, threshold_px=thr)
            conf[t] = np.where(tri.inliers, conf[t], 0.0)
            self.tri.append(tri)
        self.kp, self.conf = kp, conf


# -- placement -----------------------------------------------------------------------------------

def _hull_extent(views: list[MaskView], step: float = 0.05) -> tuple[np.ndarray, float, float]:
    """Centre (x, y), lowest and highest z of the masks' visual hull (coarse voxels)."""
    cams = [v.camera for v in views]
    # the point nearest to every optical axis: where the rig looks
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:
        d = c.c2w[:3, 2]
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ c.center
    centre = np.linalg.lstsq(A, b, rcond=None)[0]
    xs = np.arange(-1.2, 1.2 + 1e-9, step)
    zs = np.arange(-2.0, 2.0 + 1e-9, step)
    X, Y, Z = np.meshgrid(xs + centre[0], xs + centre[1], zs + centre[2], indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    inside = np.ones(len(P), bool)
    seen = np.zeros(len(P), int)
    for v in views:
        uv, z = v.camera.project(P)
        u, w = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        vis = (z > 0) & (u >= 0) & (w >= 0) & (u < v.camera.width) & (w < v.camera.height)
        ok = np.zeros(len(P), bool)
        ok[vis] = v.mask[w[vis], u[vis]]
        inside &= ok | ~vis
        seen += vis
    inside &= seen >= 2
    if inside.sum() < 10:
        raise PhysavatarError(None, "body fit: the masks of the first frame have no common foreground "
                                    "(is the calibration consistent with the images?)")
    Q = P[inside]
    return np.median(Q[:, :2], 0), float(np.percentile(Q[:, 2], 0.5)), float(np.percentile(Q[:, 2], 99.5))


def _heading_from_keypoints(tri) -> float | None:
    """Yaw that turns the rest body (left at +x) to the triangulated shoulders and hips."""
    pairs = [(11, 12), (23, 24)]
    left = [tri.points[a] - tri.points[b] for a, b in pairs if tri.ok[a] and tri.ok[b]]
    if not left:
        return None
    d = np.mean(left, 0)
    return float(np.arctan2(d[1], d[0]))
