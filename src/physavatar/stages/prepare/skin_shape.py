"""The body's shape from the skin (:mod:`.body_fit`'s first phase, session 35).

The first frame's fit draws the phenotypes towards Anny's default (its shape prior), and without
that prior the silhouettes and the clothed mesh of a dress pull the hidden hips and thighs one
way for any body under it (docs/prepare.md, session 34). Here the shape is fitted again from
what the clothing does not hide:

- **skin**: the fitted body's vertices within ``skin_distance`` of the clothed mesh (the visual
  hull is tight on bare arms, the head and the lower legs, and centimetres off the body under a
  skirt or a loose top; the hands' and feet's extremities, which a remeshed hull does not
  resolve, are left out);
- the terms, on the first frame: the mask contour points whose nearest projected body point is
  skin (the contours of the clothing are dropped); the body inside every mask (unbiased: the
  clothing covers the body); the body inside the clothed mesh, with no clothing margin where it
  is skin; the skin on the clothed mesh from both sides (robust, ``w_skin_surface``: a dense 3D
  term, where the contours see only outlines); the clothed vertices nearest to skin drawn onto
  it; the keypoints when there are any; a weak shape prior (``w_shape_prior_skin``);
- pose and phenotypes together by Adam, the phenotypes' steps in metres of the rest body (they
  move it from under 0.5 mm to 84 mm per 0.1, so Adam's steps in phenotype units are too long
  for age and height and too short for the rest), the kernel narrowing to ``sigma_end``;
- from several starts (``skin_starts``): the fitted phenotypes, and those with age moved by
  ±0.15 and height by what keeps the stature (a younger, taller body and an older, shorter one
  have nearly the same outline; one start stays in its valley). The start whose fit ends with
  the lowest loss wins.

Measured in docs/prepare.md (session 35).
"""

from __future__ import annotations

import numpy as np
import torch

from ...body.differentiable import DTYPE
from ...body.model import BodyShape


def skin_vertices(clothing, V: np.ndarray, exclude: np.ndarray, distance: float) -> np.ndarray:
    """[V] bool: body vertices ``V`` [V, 3] within ``distance`` [m] of the clothed surface
    (``ClothedSurface``: along the nearest clothed vertex's normal, either side), not in
    ``exclude`` [V] bool."""
    with torch.no_grad():
        s = clothing.signed_distance(torch.as_tensor(np.asarray(V), dtype=DTYPE)).numpy()
    return (np.abs(s) < distance) & ~np.asarray(exclude, bool)


def skin_shape(fitter, rot: torch.Tensor, tau: torch.Tensor, phen: torch.Tensor):
    """The first frame's phenotypes fitted again from the skin (module doc); returns
    (rot, tau, phen, info)."""
    cfg, body = fitter.cfg, fitter.model.body
    before = phen.numpy().copy()
    with torch.no_grad():
        V, _ = fitter.model.pose(rot, tau, phen)
    skin = skin_vertices(fitter.clothing, V[0].numpy(), ~np.isin(np.arange(V.shape[1]), fitter.clothing_points.numpy()),
                         cfg.skin_distance)
    info = {"skin_share": round(float(skin.mean()), 3), "shape_before": [round(float(x), 4) for x in before]}
    if skin.sum() < 10:
        info["note"] = "skipped: the clothed mesh is near almost none of the body"
        return rot, tau, phen, info
    sk = torch.as_tensor(skin)
    fitter.skin, fitter.skin_samples = sk, torch.cat([sk, sk[fitter.sample_faces].all(1)])
    best = None
    try:
        for delta in cfg.skin_starts or (0.0,):
            r = _candidate(fitter, rot, tau, phen, delta)
            info.setdefault("candidates", []).append({"start_age_offset": delta, "loss": r[3],
                                                      "shape": [round(float(x), 4) for x in r[2]]})
            if best is None or r[3] < best[3]:
                best = r
    finally:
        fitter.skin = fitter.skin_samples = None
    rot, tau, ph, loss = best
    body.relinearize(BodyShape.from_array(ph.numpy()))
    info["shape_after"] = [round(float(x), 4) for x in ph]
    info["loss"] = loss
    return rot, tau, ph, info


def _stature_direction(body) -> np.ndarray:
    """[6] the phenotype direction (age +1, height as much as keeps the rest body's stature)."""
    from ...body.model import PHENOTYPES

    ia, ih = PHENOTYPES.index("age"), PHENOTYPES.index("height")
    v0, J = body.v0.numpy(), body.Jv.numpy()
    top, bottom = int(v0[:, 2].argmax()), int(v0[:, 2].argmin())
    s = J[:, top, 2] - J[:, bottom, 2]  # d stature / d phenotype
    d = np.zeros(len(PHENOTYPES))
    d[ia], d[ih] = 1.0, -s[ia] / s[ih]
    return d


def _candidate(fitter, rot, tau, phen, delta: float):
    """The skin fit from the phenotypes moved by ``delta`` along the equal-stature direction:
    (rot, tau, phen, loss)."""
    cfg, body = fitter.cfg, fitter.model.body
    centre = fitter.shape_centre()
    body.relinearize(BodyShape.from_array(phen.numpy()))
    start = torch.as_tensor(np.clip(phen.numpy() + delta * _stature_direction(body), 0.0, 1.0), dtype=DTYPE)
    with torch.no_grad():
        z0 = float(fitter.model.pose(rot, tau, phen)[0][0, :, 2].min())
        body.relinearize(BodyShape.from_array(start.numpy()))
        tau = tau.clone()
        tau[0, 2] += z0 - float(fitter.model.pose(rot, tau, start)[0][0, :, 2].min())  # feet where they were
    rot, tau = rot.clone().requires_grad_(), tau.clone().requires_grad_()

    def total(sigma, p, shape_prior=True):
        V, H = fitter.model.pose(rot, tau, p)
        loss = fitter.data_loss([0], V, H, sigma, rot) + fitter.prior(rot)
        return loss + cfg.w_shape_prior_skin * ((p - centre) ** 2).sum() if shape_prior else loss

    ph = _adam(fitter, rot, tau, start, total)
    fitter._run([rot, tau], [0.02, 0.005], cfg.frame_iterations, lambda s: total(s, ph, False), cfg.sigma_end,
                cfg.sigma_end)
    with torch.no_grad():
        loss = float(total(cfg.sigma_end, ph))
    return rot.detach(), tau.detach(), ph, loss


def _adam(fitter, rot, tau, start, total) -> torch.Tensor:
    """Pose and phenotypes together by Adam from phenotypes ``start``, the phenotypes in metres:
    each one's step scaled by how far it moves the rest body (rms over the vertices), so that age
    (84 mm per 0.1) and muscle (under 0.5 mm) move the body alike; re-linearised every
    ``relinearize_every``. Returns the phenotypes."""
    cfg, body = fitter.cfg, fitter.model.body
    iters = cfg.skin_iterations
    lrs = (0.01, 0.003, cfg.skin_step)
    base = start.clone()
    u = torch.zeros_like(base, requires_grad=True)  # [6] m: phenotypes = base + u / scale

    def metres():
        return body.Jv.pow(2).sum(-1).mean(-1).sqrt().clamp(min=1e-4)  # [6] m per unit phenotype

    scale = metres()
    opt = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in zip((rot, tau, u), lrs)])
    for it in range(iters):
        frac = it / max(iters - 1, 1)
        sigma = cfg.sigma_end * cfg.skin_sigma_factor ** (1 - frac)
        for g, lr in zip(opt.param_groups, lrs):
            g["lr"] = lr * (1.0 if frac < 0.7 else 0.2)
        opt.zero_grad()
        total(sigma, base + u / scale).backward()
        opt.step()
        with torch.no_grad():  # trust region of the linearised shape, inside [0, 1]
            lo, hi = (body.p0 - cfg.shape_step).clamp(min=0.0), (body.p0 + cfg.shape_step).clamp(max=1.0)
            u.copy_((torch.maximum(torch.minimum(base + u / scale, hi), lo) - base) * scale)
            if (it + 1) % cfg.relinearize_every == 0 or it + 1 == iters:
                base = base + u / scale
                u.zero_()
                body.relinearize(BodyShape.from_array(base.numpy()))
                scale = metres()
    return base
