"""How far a keypoint detector's landmarks lie from the Anny joints the body fit maps them to
(docs/prepare.md, "Session 24"), on a synthetic capture whose true body is known.

    python benchmarks/prepare_landmarks.py --demo DEMO/capture [--keypoints FILE.npz] [--results FILE]

Needs the ``keypoints`` extra (MediaPipe) unless ``--keypoints`` gives the detections
(``keypoints`` [T, C, 33, 2] px, ``confidence`` [T, C, 33], as prepare/keypoints.npz holds them).
Each frame's detections are triangulated as the body fit does (RANSAC over views) and compared
with the true body's model keypoints (``fit_model._Model.keypoints``: a bone's head or a picked
surface point). Per keypoint: the mean offset in the body's frame (the root's: x the body's left,
y its back, z up) and its spread over the frames, in mm, and the median 2D distance in px. The
body fit's ``landmark_offsets`` estimate the former at the first frame.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import cpu_name


def main() -> None:
    from physavatar.body.differentiable import DTYPE, DiffBody, axis_angle_to_matrix_t
    from physavatar.capture import load_capture
    from physavatar.progress import resolve
    from physavatar.stages.prepare.body_fit import BodyFitConfig
    from physavatar.stages.prepare.fit_model import _Model
    from physavatar.stages.prepare.keypoints import detect_capture, make_detector, triangulate

    ap = argparse.ArgumentParser()
    ap.add_argument("--demo", type=Path, default=HERE.parent / "demo_out" / "capture")
    ap.add_argument("--keypoints", type=Path, default=None)
    ap.add_argument("--results", type=Path, default=HERE / "results" / "prepare_landmarks_demo.json")
    args = ap.parse_args()
    cap = load_capture(args.demo)
    if cap.body is None:
        sys.exit(f"{args.demo}: no body.npz (the true body is needed)")
    if args.keypoints is not None:
        z = np.load(args.keypoints)
        kp, conf = z["keypoints"], z["confidence"]
    else:
        det, _ = make_detector("mediapipe")
        kp, conf = detect_capture(args.demo, cap.cameras, list(cap.frames), det, resolve(None))
    tb = cap.body
    m = _Model(BodyFitConfig())
    pos = {n: i for i, n in enumerate(tb.bone_names)}
    R = np.zeros((len(tb.rotations), m.B, 3))
    for j, n in enumerate(m.body.bone_names):
        if n in pos:
            R[:, j] = tb.rotations[:, pos[n]]
    phen = torch.as_tensor(tb.shape.as_array(), dtype=DTYPE)
    tau = torch.as_tensor(tb.root_translation + [0.0, 0.0, DiffBody.floor_offset(tb.shape)], dtype=DTYPE)
    with torch.no_grad():
        Rt = torch.as_tensor(R, dtype=DTYPE)
        V, H = m.body.pose(Rt, tau, phen)
        K = m.keypoints(V, H).numpy()  # [T, K, 3]
        R0 = axis_angle_to_matrix_t(Rt[:, m.body.bone_names.index("root")]).numpy()  # [T, 3, 3]
    cams = cap.cameras
    thr = np.array([0.04 * max(c.width, c.height) for c in cams])
    body_frame = {k: [] for k in m.kp_ids}
    px = {k: [] for k in m.kp_ids}
    for t in range(len(kp)):
        tri = triangulate(kp[t], conf[t], cams, threshold_px=thr)
        for j, k in enumerate(m.kp_ids):
            if tri.ok[k]:
                body_frame[k].append(R0[t].T @ (tri.points[k] - K[t, j]))
            for c, cam in enumerate(cams):
                if conf[t, c, k] > 0 and tri.inliers[c, k]:
                    px[k].append(float(np.linalg.norm(kp[t, c, k] - cam.project(K[t, j][None])[0][0])))
    out = {}
    for k in m.kp_ids:
        d = np.array(body_frame[k]) * 1000
        if not len(d):
            continue
        out[str(k)] = {"frames": len(d), "mean_offset_mm": d.mean(0).round(1).tolist(),
                       "mean_offset_norm_mm": round(float(np.linalg.norm(d.mean(0))), 1),
                       "spread_mm": round(float(np.sqrt(((d - d.mean(0)) ** 2).sum(1).mean())), 1),
                       "first_frame_mm": d[0].round(1).tolist() if len(body_frame[k]) == len(kp) else None,
                       "median_px": round(float(np.median(px[k])), 1) if px[k] else None}
        print(f"{k:3d} offset {out[str(k)]['mean_offset_mm']} mm (|{out[str(k)]['mean_offset_norm_mm']}|), "
              f"spread {out[str(k)]['spread_mm']} mm, {out[str(k)]['median_px']} px")
    result = {"benchmark": "prepare_landmarks", "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": {"cores": os.cpu_count(), "cpu": cpu_name(), "gpu": None},
              "capture": str(args.demo), "frames": len(kp), "cameras": len(cams),
              "image_size": [cams[0].width, cams[0].height], "keypoints": out,
              "checks": {"landmarks_measured": {"value": len(out), "target": "reported", "pass": len(out) > 0}}}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
