"""The cameras' calibration checked and corrected against the person (``physavatar prepare``).

A real rig's calibration is often a few pixels off for the video it comes with (cameras nudged
after calibrating, a calibration of another session or resolution). The person is then a
calibration object: the same body point detected in every view must project to its detections
in all of them. Each camera gets an **image offset** (its principal point moved by ``(du, dv)``
pixels, to first order a small turn of the camera), estimated together with the 3D keypoints of
every frame by a robust bundle adjustment (scipy's ``least_squares``, soft-L1 loss) of the
detector's 2D keypoints (the views that the RANSAC triangulation keeps); a weak prior on the
offsets fixes the directions the data leave free (a common 3D shift of everything).

Keypoints carry the detector's own view-dependent bias, so the correction is **checked against
the silhouettes**, which it did not see: the masks' visual hull (voxel carving) of a few frames is
projected back into every camera, and the share of each mask it covers is compared with the
original and the corrected cameras. Cameras that disagree carve the hull too small, so the
coverage rises when a correction is right. The correction is kept only when the worst camera's
coverage rises (:func:`refine_cameras`).
"""

from __future__ import annotations

import numpy as np

from ...camera import Camera
from .keypoints import triangulate

# MediaPipe's hips sit above and outside the joints, differently from the front and the back
EXCLUDED = (23, 24)


def shifted(cam: Camera, offset) -> Camera:
    """``cam`` with its principal point moved by ``offset`` = (du, dv) pixels."""
    K = cam.K.copy()
    K[0, 2] += float(offset[0])
    K[1, 2] += float(offset[1])
    return Camera(cam.name, cam.width, cam.height, K, cam.w2c)


def keypoint_offsets(cams: list[Camera], kp: np.ndarray, conf: np.ndarray, *, min_conf: float = 0.5,
                     loss_px: float = 0.005, prior_px: float = 0.05, ransac: float = 0.04) -> tuple[np.ndarray, dict]:
    """Per-camera image offsets [C, 2] px that make the keypoints' views agree.

    Args:
        cams: the C cameras (the keypoints' resolution).
        kp: [T, C, K, 2] detections px; conf: [T, C, K] in [0, 1].
        loss_px, prior_px, ransac: the soft-L1 scale, the offsets' prior scale and the RANSAC
            inlier threshold, as shares of each camera's longer side.
    Returns:
        offsets [C, 2] and a report (observations per camera, median residual before / after).
    """
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    T, C, K = conf.shape
    size = np.array([max(c.width, c.height) for c in cams], np.float64)
    P = np.stack([c.K @ c.w2c[:3] for c in cams])
    obs_cam, obs_pt, obs_uv, obs_w, X0 = [], [], [], [], []
    for t in range(T):
        tri = triangulate(kp[t], conf[t], cams, min_conf=min_conf, threshold_px=ransac * size)
        for k in range(K):
            if k in EXCLUDED or not tri.ok[k]:
                continue
            views = np.flatnonzero(tri.inliers[:, k] & (conf[t, :, k] >= min_conf))
            if len(views) < 2:
                continue
            for c in views:
                obs_cam.append(c)
                obs_pt.append(len(X0))
                obs_uv.append(kp[t, c, k])
                obs_w.append(conf[t, c, k])
            X0.append(tri.points[k])
    n = len(obs_cam)
    counts = np.bincount(np.asarray(obs_cam, int), minlength=C) if n else np.zeros(C, int)
    info = {"observations": {c.name: int(m) for c, m in zip(cams, counts)}}
    if n == 0 or (counts < 20).any():
        return np.zeros((C, 2)), info | {"skipped": "fewer than 20 keypoint observations in a camera"}
    oc, op = np.asarray(obs_cam), np.asarray(obs_pt)
    uv, w = np.asarray(obs_uv), np.sqrt(np.asarray(obs_w))
    N = len(X0)
    s_obs = size[oc][:, None]

    # the offsets a common 3D shift of the person explains (J_c d in camera c, J_c the projection's
    # Jacobian at the keypoints' centre) are left to the points: the offsets are held orthogonal
    # to them (a strong residual), so the world stays put
    J = np.concatenate([_projection_jacobian(c, np.mean(X0, 0)) for c in cams])  # [2C, 3]
    Q = np.linalg.qr(J)[0]  # [2C, 3] orthonormal

    def residuals(x):
        d = x[:2 * C].reshape(C, 2)
        X = x[2 * C:].reshape(N, 3)
        h = np.einsum("nij,nj->ni", P[oc], np.concatenate([X[op], np.ones((n, 1))], 1))
        proj = h[:, :2] / h[:, 2:3] + d[oc]
        r = w[:, None] * (proj - uv) / (loss_px * s_obs)
        return np.concatenate([r.ravel(), (d / (prior_px * size[:, None])).ravel(), 100.0 * (Q.T @ d.ravel())])

    A = lil_matrix((2 * n + 2 * C + 3, 2 * C + 3 * N), dtype=np.int8)
    rows = np.arange(n)
    for j in range(2):
        A[2 * rows + j, 2 * oc + j] = 1
        for a in range(3):
            A[2 * rows + j, 2 * C + 3 * op + a] = 1
    A[2 * n + np.arange(2 * C), np.arange(2 * C)] = 1
    A[2 * n + 2 * C:, :2 * C] = 1
    x0 = np.concatenate([np.zeros(2 * C), np.asarray(X0).ravel()])
    sol = least_squares(residuals, x0, jac_sparsity=A, loss="soft_l1", f_scale=1.0, x_scale="jac", max_nfev=200)
    off = sol.x[:2 * C].reshape(C, 2)

    def median_px(x):
        r = residuals(x)[:2 * n].reshape(n, 2) * (loss_px * s_obs) / w[:, None]
        return float(np.median(np.linalg.norm(r, axis=1)))

    info |= {"median_residual_px_before": round(median_px(x0), 2),
             "median_residual_px_after": round(median_px(sol.x), 2)}
    return off, info


def _projection_jacobian(cam: Camera, X: np.ndarray) -> np.ndarray:
    """[2, 3] derivative of ``cam``'s pixel coordinates with respect to world point ``X``."""
    pc = cam.world_to_camera(X[None])[0]
    fx, fy = cam.K[0, 0], cam.K[1, 1]
    x, y, z = pc
    Jc = np.array([[fx / z, 0.0, -fx * x / z ** 2], [0.0, fy / z, -fy * y / z ** 2]])
    return Jc @ cam.w2c[:3, :3]


def hull_coverage(cams: list[Camera], masks: list[np.ndarray], voxel: float = 0.015) -> np.ndarray:
    """[C] share of each camera's mask (bool [H, W]) that the masks' visual hull, projected back,
    covers: voxel carving (every voxel that all cameras see must be in every mask), coarse then at
    ``voxel`` around the coarse hull; a voxel is drawn as a disk of its projected radius."""
    import cv2

    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:  # the point nearest to every optical axis: where the rig looks
        d = c.c2w[:3, 2]
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ c.center
    centre = np.linalg.lstsq(A, b, rcond=None)[0]

    def carve(lo, hi, step):
        axes = [np.arange(lo[i], hi[i] + 1e-9, step) for i in range(3)]
        P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        inside = np.ones(len(P), bool)
        for c, m in zip(cams, masks):
            uv, z = c.project(P)
            u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            vis = (z > 0) & (u >= 0) & (v >= 0) & (u < c.width) & (v < c.height)
            ok = np.zeros(len(P), bool)
            ok[vis] = m[v[vis], u[vis]]
            inside &= ok
        return P[inside]

    Q = carve(centre - [1.5, 1.5, 2.5], centre + [1.5, 1.5, 2.5], 0.05)
    if len(Q) == 0:
        return np.zeros(len(cams))
    Q = carve(Q.min(0) - 0.05, Q.max(0) + 0.05, voxel)
    out = np.zeros(len(cams))
    for i, (c, m) in enumerate(zip(cams, masks)):
        uv, z = c.project(Q)
        r = max(1, int(np.ceil(0.5 * voxel * c.K[0, 0] / np.median(z))))
        img = np.zeros(m.shape, np.uint8)
        for x, y in np.round(uv).astype(int):
            if 0 <= x < c.width and 0 <= y < c.height:
                img[y, x] = 1
        img = cv2.dilate(img, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        out[i] = float((img.astype(bool) & m).sum() / max(m.sum(), 1))
    return out


# the least rise of the worst camera's hull coverage for which new cameras are taken. On the demo's
# exact cameras the body fit's offsets (at most 0.17 px) raised it by 0.0002, a tie, and were
# applied after the hull had been carved with the cameras as given: the hull and the cameras the
# segmentation projects it with then disagree, and the straps' tops went to the body (demo with
# MediaPipe: segmentation 97.21 -> 96.90 %, boundary 1.60 -> 6.43 cm, the same body; session 24).
# Pose2Sim's corrections raise it by 0.040 (the keypoints' offsets) and 0.012 (the body's)
MIN_COVERAGE_GAIN = 0.002


def hull_check(cams: list[Camera], new: list[Camera], masks_of, frames: list[int], check_frames: int = 3,
               min_gain: float = MIN_COVERAGE_GAIN) -> dict:
    """Whether cameras ``new`` make the masks agree better than ``cams``: the masks' hull coverage
    (:func:`hull_coverage`) of ``check_frames`` frames spread over the clip, its worst camera
    (``applied``: higher by at least ``min_gain``), and the coverages."""
    pick = np.unique(np.linspace(0, len(frames) - 1, min(check_frames, len(frames))).round().astype(int))
    before, after = np.zeros(len(cams)), np.zeros(len(cams))
    for i in pick:
        m = masks_of(frames[i])
        ms = [np.asarray(m[c.name]) > 0.5 for c in cams]
        before += hull_coverage(cams, ms) / len(pick)
        after += hull_coverage(new, ms) / len(pick)
    return {"hull_coverage_before": {c.name: round(float(v), 4) for c, v in zip(cams, before)},
            "hull_coverage_after": {c.name: round(float(v), 4) for c, v in zip(cams, after)},
            "applied": bool(after.min() >= before.min() + min_gain)}


def refine_cameras(cams: list[Camera], kp: np.ndarray, conf: np.ndarray, masks_of, frames: list[int],
                   check_frames: int = 3) -> tuple[list[Camera], dict]:
    """The cameras with the keypoints' image offsets (:func:`keypoint_offsets`) when the masks'
    hull coverage (:func:`hull_coverage`, worst camera, mean over ``check_frames`` frames spread
    over the clip) rises with them; else the cameras unchanged. ``masks_of(frame)`` -> {camera:
    [H, W] mask}."""
    off, info = keypoint_offsets(cams, kp, conf)
    info["offsets_px"] = {c.name: [round(float(x), 2) for x in o] for c, o in zip(cams, off)}
    if "skipped" in info:
        info["applied"] = False
        return cams, info
    new = [shifted(c, o) for c, o in zip(cams, off)]
    info |= hull_check(cams, new, masks_of, frames, check_frames)
    return (new if info["applied"] else cams), info


def calibrate_step(src, tmp, raw, cfg, masks_of, given: str | None, progress):
    """``prepare``'s cameras step: the keypoints detected once (``prepare/keypoints.npz``, which the
    body fit reads) and the cameras corrected when the check passes (``cameras.json`` rewritten).
    ``given``: why the capture's own body or mesh rules a correction out (they were made with its
    cameras), or None. Returns (the capture, possibly with new cameras; one line; numbers or None)."""
    from dataclasses import replace

    from ...capture import save_cameras
    from ...files import save_npz_atomic
    from .keypoints import detect_capture, make_detector

    if not cfg.calibrate:
        return raw, "given (not checked: --no-calibrate)", None
    if given:
        return raw, f"given (not checked: {given})", None
    if len(raw.cameras) < 3:
        return raw, "given (not checked: fewer than 3 cameras)", None
    try:
        detector, note = make_detector("auto" if cfg.body.keypoints == "mediapipe" else cfg.body.keypoints)
    except ImportError:
        detector, note = None, ""
    if detector is None:
        return raw, "given (not checked: no keypoint detector)", None
    kp, conf = detect_capture(tmp, raw.cameras, raw.frames, detector, progress)
    save_npz_atomic(tmp / "prepare" / "keypoints.npz", keypoints=kp, confidence=conf, frames=np.asarray(raw.frames))
    with progress.task("prepare: checking the cameras", total=1) as task:
        cams, info = refine_cameras(raw.cameras, kp, conf, masks_of, raw.frames)
        task.advance()
    if not info["applied"]:
        return raw, "given (checked: the keypoints' correction does not help the masks' hull, not applied)", info
    save_cameras(tmp, cams)
    worst = max(np.hypot(*o) for o in info["offsets_px"].values())
    return replace(raw, cameras=cams), f"corrected: image offsets from the keypoints (up to {worst:.1f} px), " \
                                       "checked against the masks' hull", info
