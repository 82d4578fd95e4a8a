"""A detector's landmarks are not Anny's joints (stages/prepare/body_fit.py, ``landmark_offsets``,
``press_with_mesh_below``).

On the demo's renders MediaPipe's landmarks sit centimetres from the true body's joints, the same
way in every frame (triangulated over the 10 cameras and 48 frames, against the true body:
ankles 4.5 cm above Anny's, shoulders 2.5 cm above and 1.5 cm inside, hips 2-3 cm inside; session
24). Fitted as if they were joints, they pulled the first frame 13 mm from the truth (5 mm without
keypoints). Here a body of known pose is seen by six cameras (exact silhouettes, a clothed mesh 3 mm
over it) with keypoints that are its own joints moved by known offsets in the body's frame; the
first frame's fit must land on the true body and find those offsets.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from physavatar.body.motion import builtin_motion
from physavatar.camera import ring_rig

# landmark offsets in the body's frame [m] (x: the body's left, y: its back, z: up), by MediaPipe
# index: about what the demo's detector shows (shoulders up and in, hips in and forward, knees and
# ankles up, the nose behind the tip)
BIAS = {0: (0.0, 0.035, 0.015), 11: (-0.015, 0.0, 0.025), 12: (0.015, 0.0, 0.025),
        13: (-0.015, 0.0, 0.02), 14: (0.015, 0.0, 0.02), 23: (-0.025, -0.02, 0.0), 24: (0.025, -0.02, 0.0),
        25: (-0.02, 0.0, 0.03), 26: (0.02, 0.0, 0.03), 27: (0.0, 0.0, 0.045), 28: (0.0, 0.0, 0.045)}


class _Task:
    def advance(self, **_):
        pass


class _Observations:
    """What body_fit._Observations holds, made from a known body: masks rasterised from its
    triangles, keypoints projected from its joints plus ``BIAS`` (turned with the root)."""

    def __init__(self, model, rot, tau, phen, cams):
        import cv2

        from physavatar.body.differentiable import axis_angle_to_matrix_t
        from physavatar.body.fit_terms import MaskView
        from physavatar.stages.prepare.keypoints import N_LANDMARKS, triangulate

        with torch.no_grad():
            V, H = model.pose(rot, tau, phen)
            K = model.keypoints(V, H)[0].numpy()
            R0 = axis_angle_to_matrix_t(rot[:, 0])[0].numpy()
        self.V = V[0].numpy()
        self.cams, self.native, self.frames = cams, cams, [0]
        rng = np.random.default_rng(0)
        self._views = []
        for c in cams:
            uv, _ = c.project(self.V)
            img = np.zeros((c.height, c.width), np.uint8)
            for f in model.body.faces:
                cv2.fillConvexPoly(img, np.round(uv[f] * 16).astype(np.int32), 1, shift=4)
            self._views.append(MaskView.build(c, img > 0, 300, rng))
        self.bias = np.zeros((len(model.kp_ids), 3))
        for j, k in enumerate(model.kp_ids):
            self.bias[j] = BIAS.get(k, (0.0, 0.0, 0.0))
        X = K + self.bias @ R0.T
        self.kp = np.zeros((1, len(cams), N_LANDMARKS, 2))
        self.conf = np.zeros((1, len(cams), N_LANDMARKS))
        for c, cam in enumerate(cams):
            self.kp[0, c, model.kp_ids] = cam.project(X)[0]
            self.conf[0, c, model.kp_ids] = 1.0
        self.tri = [triangulate(self.kp[0], self.conf[0], cams, threshold_px=8.0)]

    def views(self, t):
        return self._views


def _first_frame(**changes):
    """(mean vertex error [m] of the fitted first frame, fitted landmark offsets or None, bias)."""
    from physavatar.body.differentiable import DTYPE
    from physavatar.body.fit_terms import ClothedSurface
    from physavatar.geometry.mesh import vertex_normals
    from physavatar.stages.prepare.body_fit import BodyFitConfig, _Fitter
    from physavatar.stages.prepare.fit_model import _Model

    # the skin pass (session 35, tests/test_body_fit_skin.py) off: it moves both fits here (with it
    # 4.5 and 7.7 mm) and the landmarks' part is what is measured
    cfg = dataclasses.replace(BodyFitConfig(keypoints="none"), first_iterations=150, fit_thumbs=False,
                              skin_shape=False, **changes)
    model = _Model(cfg)
    names = model.body.bone_names
    motion = builtin_motion("walk", names, 25.0, 1.0)
    rot = torch.as_tensor(motion.rotations[6][None][:, model.active.numpy()], dtype=DTYPE)
    rot[0, 0, 2] += 0.3  # turned 17 degrees from the rig's front camera
    phen = model.body.p0.clone()
    with torch.no_grad():
        zmin = float(model.pose(rot, torch.zeros(1, 3, dtype=DTYPE), phen)[0][0, :, 2].min())
    tau = torch.tensor([[0.05, -0.03, -zmin]], dtype=DTYPE)
    cams = ring_rig(6, 3.0, 1.0, (0.0, 0.0, 0.9), 256, 256, 45.0)
    obs = _Observations(model, rot, tau, phen, cams)
    clothed = obs.V + 0.003 * vertex_normals(obs.V, model.body.faces)
    fitter = _Fitter(cfg, obs, ClothedSurface(clothed, model.body.faces), 25.0)
    r, t, p, _ = fitter.first_frame(_Task())
    with torch.no_grad():
        V = fitter.model.pose(r, t, p)[0][0].numpy()
    err = float(np.linalg.norm(V - obs.V, axis=1).mean())
    off = None if fitter.kp_offsets is None else fitter.kp_offsets.numpy()
    return err, off, obs.bias


def test_landmark_offsets_keep_the_first_frame_on_the_true_body():
    new, off, bias = _first_frame()
    old, _, _ = _first_frame(landmark_offsets=False, press_with_mesh_below=100)
    # the fitted offsets are the landmarks' (measured: 6.3 mm off on average, 10.8 at most)
    assert off is not None, "no landmark offsets fitted"
    big = np.linalg.norm(bias, axis=1) > 0
    assert np.linalg.norm(off[big] - bias[big], axis=1).mean() < 0.01, (off[big], bias[big])
    # measured: the body 14.2 mm from the truth with the landmarks taken for joints and the first
    # frame pressed into the masks (the session-23 fit), 5.1 mm now; with the offsets but the
    # press (a 1-px margin is 1 cm here) 14.9 mm
    assert new < 0.0075, (new, old)
    assert old > 2 * new, (new, old)
