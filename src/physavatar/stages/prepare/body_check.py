"""The body fit's check (:mod:`.body_fit`): how the fitted body agrees with what it was fitted to."""

from __future__ import annotations

import numpy as np
import torch

from ...body.fit_terms import project, sample_field

# -- the check -----------------------------------------------------------------------------------

def check(fitter, rot, tau, phen) -> dict:
    """The fitted body against its observations (body_fit.py's report): the share of the projected
    body inside each mask, keypoint reprojection errors, penetration of the clothed mesh, jitter."""
    obs, model = fitter.obs, fitter.model
    with torch.no_grad():
        V, H = model.pose(rot, tau, phen)
        kps = model.keypoints(V, H) if obs.kp is not None else None
    V, H = V.numpy(), H.numpy()
    T = len(V)
    share = np.zeros((T, len(obs.cams)))
    near = np.zeros((T, len(obs.cams)))
    for t in range(T):
        for c, view in enumerate(obs.views(t)):
            uv, z = project(torch.as_tensor(V[t]), view.camera)
            H_, W_ = view.mask.shape
            inimg = ((uv[:, 0] >= -0.5) & (uv[:, 1] >= -0.5) & (uv[:, 0] <= W_ - 0.5) & (uv[:, 1] <= H_ - 0.5)
                     & (z > 0)).numpy()
            sd = sample_field(view.dt, uv).numpy()  # signed distance to the mask's edge [px]
            share[t, c] = (inimg & (sd <= 0)).mean()
            near[t, c] = (inimg & (sd <= 1.0)).mean()
    rep = {"inside_masks": {
        "mean": round(float(share.mean()), 4),
        "mean_within_1px": round(float(near.mean()), 4),
        "per_camera_mean": {c.name: round(float(s), 4) for c, s in zip(obs.native, share.mean(0))},
        "per_camera_worst_frame": {c.name: round(float(s), 4) for c, s in zip(obs.native, share.min(0))},
        "pixel_mm": round(1000 * float(np.median([np.linalg.norm(c.center - V[0].mean(0)) / c.K[0, 0]
                                                 for c in obs.cams])), 1)}}
    if kps is not None:
        errs = {c.name: [] for c in obs.native}
        per_kp = {k: [] for k in fitter.kp_ids}
        for t in range(T):
            for c, (cam, nat) in enumerate(zip(obs.cams, obs.native)):
                uv, _ = cam.project(kps[t].numpy())
                sel = obs.conf[t, c, fitter.kp_ids] > 0.5
                d = np.linalg.norm(uv - obs.kp[t, c, fitter.kp_ids], axis=1)[sel] * nat.width / cam.width
                errs[nat.name] += d.tolist()
                for k, e in zip(np.asarray(fitter.kp_ids)[sel], d):
                    per_kp[k].append(e)
        allv = sum(errs.values(), [])
        rep["keypoints_px"] = {"median": round(float(np.median(allv)), 2) if allv else None,
                               "per_camera_median": {k: round(float(np.median(v)), 2) if v else None
                                                     for k, v in errs.items()},
                               "count": len(allv),
                               # a limb lost inside another's silhouette shows here, not in the masks' share
                               "per_keypoint_median": {str(k): round(float(np.median(v)), 1) for k, v in per_kp.items() if v}}
        if rep["keypoints_px"]["per_keypoint_median"]:
            k, v = max(rep["keypoints_px"]["per_keypoint_median"].items(), key=lambda kv: kv[1])
            rep["keypoints_px"]["worst_keypoint"] = {"mediapipe_index": int(k), "median_px": v}
    if fitter.clothing is not None:
        s = fitter.clothing.signed_distance(torch.as_tensor(V[0])[fitter.clothing_points]).numpy()
        rep["clothing_first_frame"] = {"share_outside": round(float((s > 0).mean()), 4),
                                       "max_outside_mm": round(float(max(s.max(), 0.0)) * 1000, 1),
                                       "depth_p95_mm": round(float(np.percentile(s, 95)) * 1000, 1)}
    joints = H[:, fitter.model.active.numpy()]
    if T >= 3:
        acc = np.linalg.norm(joints[2:] - 2 * joints[1:-1] + joints[:-2], axis=-1) * fitter.fps ** 2
        rep["jitter"] = {"joint_acceleration_mean_m_s2": round(float(acc.mean()), 3),
                         "joint_acceleration_max_m_s2": round(float(acc.max()), 3)}
    return rep
