"""The body fit's keypoint term reaches a limb far from its keypoints (stages/prepare/body_fit.py).

On the Pose2Sim clip the per-frame fit, started from the previous frames, had put an arm inside
the torso's silhouette (where the silhouettes do not see it) 27-39 cm from its triangulated
keypoints, and the keypoint term's 5 cm robust kernel no longer pulled it. Here an Anny arm starts
at rest and its keypoints (shoulder, elbow, wrist: exact projections into four cameras of the
same body with the arm raised) lie 30-40 cm away, and a weak pull to the start stands for the
silhouettes that hold it; the fit's keypoint term alone, with its
kernel's floor at the default ``kp_sigma`` and at the old 5 cm, moves the arm.
"""

from __future__ import annotations

import numpy as np
import torch

from physavatar.camera import ring_rig


def _fit_arm(kp_sigma: float, iters: int = 150) -> float:
    from physavatar.body.fit_terms import keypoint_term
    from physavatar.stages.prepare.body_fit import BodyFitConfig
    from physavatar.stages.prepare.fit_model import _Model

    cfg = BodyFitConfig(keypoints="none")
    model = _Model(cfg)
    cams = ring_rig(4, 3.0, 1.0, (0, 0, 0.9), 256, 256, 40.0)
    phen = torch.full((6,), 0.5, dtype=torch.float64)
    A = len(cfg.bones)
    arm = [cfg.bones.index(b) for b in ("upperarm01.L", "lowerarm01.L")]
    truth = torch.zeros(1, A, 3, dtype=torch.float64)
    truth[0, arm[0]] = torch.tensor([0.6, 0.0, 0.4], dtype=torch.float64)  # raised forward and out
    truth[0, arm[1]] = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
    tau = torch.zeros(1, 3, dtype=torch.float64)
    with torch.no_grad():
        V, H = model.pose(truth, tau, phen)
        X = model.keypoints(V, H)[0].numpy()
    kp2d = np.stack([c.project(X)[0] for c in cams])
    conf = np.ones(kp2d.shape[:2])
    ids = np.array(model.kp_ids)
    sel = np.isin(ids, [11, 13, 15])  # the left arm's keypoints only
    conf[:, ~sel] = 0.0
    rot = torch.zeros(1, A, 3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([rot], lr=0.03)
    mask = torch.zeros(1, A, 1, dtype=torch.float64)
    mask[0, arm] = 1.0
    for _ in range(iters):
        opt.zero_grad()
        V, H = model.pose(rot * mask, tau, phen)
        # the silhouettes hold the arm where it is (inside the torso's silhouette, nothing is
        # outside a mask): here a weak pull back to the start
        hold = 2e-3 * ((rot * mask) ** 2).sum()
        loss = keypoint_term(model.keypoints(V, H)[0], kp2d, conf, cams, max(0.015, kp_sigma)) + hold
        loss.backward()
        opt.step()
    with torch.no_grad():
        V, H = model.pose(rot * mask, tau, phen)
        got = model.keypoints(V, H)[0].numpy()
    wrist = list(ids).index(15)
    return float(np.linalg.norm(got[wrist] - X[wrist]))


def test_wide_kernel_reaches_an_arm_far_from_its_keypoints():
    from physavatar.stages.prepare.body_fit import BodyFitConfig

    start = _fit_arm(0.25, iters=0)
    assert start > 0.3, start  # the arm starts far from its keypoints
    wide = _fit_arm(BodyFitConfig().kp_sigma)
    narrow = _fit_arm(0.05)
    # measured: the wrist starts 0.39 m off; 0.015 m after the fit with the 0.25 m kernel, 0.36 m with
    # the old 5 cm one (its pull at 40 cm is ~300 times weaker)
    assert wide < 0.03, (start, wide, narrow)
    assert narrow > 0.5 * start, (start, wide, narrow)


def test_outside_weight_rises_as_the_kernel_narrows():
    """With keypoints the outside term's weight goes from ``w_outside`` (kernel >= 2 s0) to
    ``w_outside_keypoints`` (kernel <= s0), geometrically; without keypoints it is ``w_outside``."""
    from physavatar.stages.prepare.body_fit import BodyFitConfig, outside_weight

    cfg = BodyFitConfig(outside_ramp_sigma=0.03, w_outside=1.0, w_outside_keypoints=20.0)
    assert outside_weight(cfg, 0.12, True) == 1.0
    assert outside_weight(cfg, 0.06, True) == 1.0
    assert np.isclose(outside_weight(cfg, 0.03 * np.sqrt(2), True), np.sqrt(20.0))
    assert outside_weight(cfg, 0.03, True) == 20.0
    assert outside_weight(cfg, 0.015, True) == 20.0
    assert outside_weight(cfg, 0.015, False) == 1.0
    assert outside_weight(BodyFitConfig(outside_ramp_sigma=0.0), 0.12, True) == BodyFitConfig().w_outside_keypoints


def test_finger_curl_closes_the_hand_towards_the_thumb():
    """One angle per hand flexes its four fingers towards the palm: the last segments' heads come
    near the thumb (a fist), not behind the hand (the reverse bend); negative angles are clamped
    (no hyperextension); the two hands mirror each other (Anny is symmetric in x)."""
    from physavatar.stages.prepare.body_fit import BodyFitConfig
    from physavatar.stages.prepare.fit_model import _Model

    m = _Model(BodyFitConfig(), curl=True)
    names = m.body.bone_names
    phen = torch.full((6,), 0.5, dtype=torch.float64)
    tau = torch.zeros(1, 3, dtype=torch.float64)

    def heads(curl_l, curl_r, reverse=False):
        rot = torch.zeros(1, m.n_params, 3, dtype=torch.float64)
        rot[0, -1, 0], rot[0, -1, 1] = curl_l, curl_r
        R = m.full_rotations(rot)
        if reverse:  # the same bend the other way, past the clamp
            for b, a in zip(m.curl_bones, m.curl_axes):
                R[0, b] = -curl_l * a
        with torch.no_grad():
            return m.body.pose(R, tau, phen)[1][0].numpy()

    def tips_to_thumb(H, s):
        tips = [names.index(f"finger{k}-3.{s}") for k in (2, 3, 4, 5)]
        return float(np.linalg.norm(H[tips] - H[names.index(f"finger1-2.{s}")], axis=1).mean())

    rest, fist, back = heads(0.0, 0.0), heads(1.4, 1.4), heads(1.4, 1.4, reverse=True)
    for s in ("L", "R"):
        # measured: 11.3 cm at rest, 4.7 cm curled, 9.8 cm bent backwards
        assert tips_to_thumb(fist, s) < 0.06 < 0.09 < tips_to_thumb(back, s) < tips_to_thumb(rest, s) + 1e-9
    np.testing.assert_allclose(heads(-0.5, -0.5), rest, atol=1e-12)  # flexion only
    L = [i for i, n in enumerate(names) if n.startswith("finger") and n.endswith(".L")]
    R = [names.index(names[i][:-1] + "R") for i in L]
    np.testing.assert_allclose(fist[L] * [-1, 1, 1], fist[R], atol=2e-3)
    one = heads(1.4, 0.0)  # each hand has its own angle
    np.testing.assert_allclose(one[R], rest[R], atol=1e-12)
    assert np.abs(one[L] - rest[L]).max() > 0.02


def test_fitted_thumb_comes_into_its_silhouettes():
    """With keypoints the thumbs' joints are fitted (``fit_thumbs``): Anny's rest thumb stands out
    from the palm, a real relaxed one lies along the index. Four cameras around the left hand see
    the silhouettes (ray-cast... here rasterised triangles) of the body with the thumb turned by a
    known rotation; from the rest thumb, the silhouette terms on the thumb's two joints alone bring
    the thumb's vertices onto the true ones."""
    import cv2

    from physavatar.body.fit_terms import MaskView, silhouette_terms
    from physavatar.stages.prepare.body_fit import BodyFitConfig
    from physavatar.stages.prepare.fit_model import THUMB_BONES, _Model

    assert _Model(BodyFitConfig(), thumbs=True).n_bones == len(BodyFitConfig().bones) + 4
    m = _Model(BodyFitConfig(), thumbs=True)
    names, bones = m.body.bone_names, m.bones
    phen = torch.full((6,), 0.5, dtype=torch.float64)
    tau = torch.zeros(1, 3, dtype=torch.float64)
    thumb = [bones.index(b) for b in THUMB_BONES[:2]]
    truth = torch.zeros(1, m.n_params, 3, dtype=torch.float64)
    truth[0, thumb[0]] = torch.tensor([0.2, -0.3, 0.5], dtype=torch.float64)
    truth[0, thumb[1]] = torch.tensor([0.0, 0.0, 0.4], dtype=torch.float64)
    with torch.no_grad():
        Vt, Ht = m.pose(truth, tau, phen)
    Vt = Vt[0].numpy()
    dom = m.body.weights.numpy().argmax(1)
    on_thumb = np.isin(dom, [names.index(f"finger1-{k}.L") for k in (1, 2, 3)])
    centre = Vt[np.isin(dom, [names.index("wrist.L")]) | on_thumb].mean(0)
    cams = ring_rig(4, 0.6, float(centre[2]) + 0.2, tuple(centre), 256, 256, 40.0)
    rng = np.random.default_rng(0)
    views = []
    for c in cams:
        uv, _ = c.project(Vt)
        img = np.zeros((c.height, c.width), np.uint8)
        for f in m.body.faces:
            cv2.fillConvexPoly(img, np.round(uv[f] * 16).astype(np.int32), 1, shift=4)
        views.append(MaskView.build(c, img > 0, 300, rng))
    rot = torch.zeros(1, m.n_params, 3, dtype=torch.float64, requires_grad=True)
    sel = torch.zeros(1, m.n_params, 1, dtype=torch.float64)
    sel[0, thumb] = 1.0
    opt = torch.optim.Adam([rot], lr=0.02)

    def thumb_error():
        with torch.no_grad():
            V, _ = m.pose(rot * sel, tau, phen)
        return float(np.linalg.norm(V[0].numpy()[on_thumb] - Vt[on_thumb], axis=1).mean())

    start = thumb_error()
    for _ in range(150):
        opt.zero_grad()
        V, _ = m.pose(rot * sel, tau, phen)
        o, c = silhouette_terms(V[0], views, 0.01)
        (50.0 * o + c).backward()
        opt.step()
    end = thumb_error()
    # measured: the thumb's vertices 47.9 mm from the truth at rest, 9.9 mm after
    assert start > 0.01, start
    assert end < 0.3 * start, (start, end)
