"""The Anny body for every frame of a capture: shape once, pose per frame.

Observations: the masks of every view (required), 2D keypoints of an offline detector when one
is installed (:mod:`.keypoints`), and the first-frame clothed mesh when given. The fit is a torch
optimisation of the differentiable Anny (:mod:`physavatar.body.differentiable`) against the
terms of :mod:`physavatar.body.fit_terms`:

1. **First frame**: phenotypes, pose and translation. The body is placed in the masks' visual
   hull (feet on its floor, centred in it); its facing comes from the triangulated shoulders and
   hips, or, without keypoints, from the best of four headings after a short fit each. Then the
   terms: body inside every mask, skin contours on the body's outline, keypoints, body inside the
   clothed mesh and near it where it is skin; weak priors on pose and shape. With keypoints and
   the mesh, each keypoint's offset from its Anny joint (a landmark is not a joint) is fitted
   here and kept for the later frames. Then, with ``skin_shape`` (``--skin-shape``) and the clothed
   mesh, pose and shape again from the skin alone, where the mesh lies on the body
   (:mod:`.skin_shape`, from several starts).
2. **Every later frame**, in order: pose and translation starting from the previous frames
   (constant velocity), with a smoothness term on the joints' acceleration.
3. **All frames together**: a few iterations on the whole sequence with the same terms, so the
   smoothness acts both ways in time.

A check at the end reports how much of the projected body falls inside each mask, keypoint
reprojection errors, penetration of the clothed mesh, and jitter (joint acceleration).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ...body.differentiable import DTYPE, DiffBody, axis_angle_to_matrix_t
from ...body.fit_terms import ClothedSurface, gm, keypoint_term, silhouette_terms
from ...body.model import PHENOTYPES, TOPOLOGIES, BodyShape
from ...errors import PhysavatarError
from ...files import read_json
from ..base import option, setting
from .body_check import check
from .fit_model import _extremities, _Model
from .observations import _heading_from_keypoints, _hull_extent, _Observations

# The bones a fit moves (the rest follow their parents): trunk, neck and head, arms to the
# wrists, legs to the feet. Twist bones (upperarm02, ...) and fingers stay at rest.
FIT_BONES = ("root", "spine05", "spine03", "spine01", "neck01", "head",
             "clavicle.L", "upperarm01.L", "lowerarm01.L", "wrist.L",
             "clavicle.R", "upperarm01.R", "lowerarm01.R", "wrist.R",
             "upperleg01.L", "lowerleg01.L", "foot.L", "upperleg01.R", "lowerleg01.R", "foot.R")


@dataclass(frozen=True)
class BodyFitConfig:
    """How the body is fitted (``physavatar prepare`` options)."""

    keypoints: str = option("auto", "2D keypoint detector: auto (mediapipe when installed), mediapipe, none",
                            flag="--keypoints", choices=("auto", "mediapipe", "none"))
    topology: str = option("collider", "Anny topology of the fitted body", flag="--body-topology",
                           choices=tuple(TOPOLOGIES))
    smoothness: float = option(0.1, "weight of the joints' acceleration against the image terms", flag="--body-smoothness",
                               check=lambda v: None if v >= 0 else "must be >= 0")
    max_resolution: int = setting(384)  # masks are fitted at most at this size (longer side, px)
    max_contour: int = setting(300)  # contour pixels per view and frame
    samples_per_face: int = setting(5)
    shape_step: float = setting(0.08)  # how far the phenotypes move between Anny evaluations
    relinearize_every: int = setting(25)  # body surface samples per triangle for the silhouettes
    first_iterations: int = setting(300)
    heading_iterations: int = setting(60)  # per candidate heading, without keypoints
    frame_iterations: int = setting(50)
    sequence_iterations: int = setting(60)
    sigma_start: float = setting(0.12)  # robust kernel of the contour term [m], annealed to ...
    sigma_end: float = setting(0.015)
    w_outside: float = setting(1.0)
    # with keypoints: they hold the pose and the heading, so the body can be pressed into the masks
    # (without them a strong outside term squeezes the body into a wrong pose: the demo's first
    # frame 8 -> 423 mm at 20); 20 -> 50 with the ramp and the margin below: Pose2Sim 90.0 -> 91.4 %
    w_outside_keypoints: float = setting(50.0)
    # [m] with keypoints, the outside weight rises from w_outside to w_outside_keypoints while the
    # kernel narrows from twice this to it: a limb that must swing through the background between
    # two silhouettes (an arm raised from beside the torso) follows its keypoints first. With the
    # full weight from the start, the Pose2Sim clip's left arm stayed inside the torso's silhouette
    # in all 20 frames (wrist 93 px from its keypoints, median); with the ramp 11 px
    outside_ramp_sigma: float = setting(0.03)
    w_contour: float = setting(1.0)
    # with keypoints (real people): the four fingers of each hand flex together by one angle per
    # hand and frame (Anny's rest hand is open; a real hand is often a fist)
    finger_curl: bool = setting(False)
    # with keypoints (real people): the thumbs' first two joints are fitted too. Anny's rest thumb
    # stands out from the palm, a relaxed hand holds it along the index; pressed into the masks
    # (w_outside_keypoints) the fitted thumb comes in (Pose2Sim, session 23: hands' vertices in
    # the masks ..., worst camera 93.7 -> 95.0 %). Without keypoints (the demo) not used
    fit_thumbs: bool = setting(True)
    # with keypoints, when prepare's cameras step may correct the cameras: each camera's image
    # offset is fitted with the body in the whole-sequence pass (session 23)
    fit_offsets: bool = setting(True)
    # with keypoints and the first-frame mesh: a detector's landmark is not an Anny joint (on the
    # demo's renders MediaPipe's ankles sit 4.5 cm above Anny's, its shoulders 2.5 cm above and
    # 1.5 cm inside, its hips 2-3 cm inside and in front; session 24). Once the first frame's pose
    # is close, each keypoint gets an offset in the body's frame, fitted with the mesh and the
    # silhouettes (so the keypoints do not pull there), and kept for the later frames
    landmark_offsets: bool = setting(True)
    # with keypoints, the frame whose clothed mesh is used (the first) is pressed into the masks like
    # the others (w_outside_keypoints, the margin) only with fewer cameras than this; with more it
    # gets w_outside and outside_margin_px. A hull carved from many views is close to the clothed
    # surface, lies inside every mask and holds the body under it: on the demo (10 cameras) the
    # press took the legs 2-4 cm off, first frame 5.6 -> 12.0 mm (session 24). From few views the
    # hull has wedges of empty space between them, its terms draw the body out into them, and the
    # press is what keeps the body in the masks: Pose2Sim (4 cameras) 96.0 % in the worst camera
    # with it, 95.2 % without
    press_with_mesh_below: int = setting(6)
    offset_lr: float = setting(0.02)  # [working px] Adam's step for the offsets
    w_offset_gauge: float = setting(100.0)
    w_offset_prior: float = setting(0.1)
    outside_margin_px: float = setting(0.0)  # the outside term's mask is shrunk by this [working px]
    # ... and by this with keypoints (they hold the pose while the body is pressed in): on the
    # Pose2Sim clip with the ramp below, body in the masks 88.0 / 86.4 % -> 90.0 / 88.0 % (mean /
    # worst camera); without keypoints not measured on the demo, so left at outside_margin_px there
    outside_margin_px_keypoints: float = setting(1.0)
    w_keypoints: float = setting(0.2)  # keypoints guide; silhouettes decide the last centimetres
    # [m] the keypoint term's robust kernel is never narrower: the keypoints are checked against
    # the other views (RANSAC triangulation), so a limb far from its keypoints is a fit stuck, not
    # a detector's mistake (a 5 cm kernel left an arm that the previous frame had put inside the
    # torso's silhouette 27-39 cm from its keypoints, where the silhouettes do not see it)
    kp_sigma: float = setting(0.25)
    w_clothing_inside: float = setting(3.0)
    w_clothing_near: float = setting(0.1)
    w_pose_prior: float = setting(2e-4)
    w_spine_twist: float = setting(0.0)  # the spine's turn about the vertical (pelvis against shoulders)
    w_shape_prior: float = setting(1e-3)
    # the phenotypes the fit starts from and its shape prior is centred on (empty: Anny's
    # defaults, all 0.5); a diagnostic: the truth here separates the shape's error from the pose's
    shape_centre: tuple = setting(())
    # session 35: after the first frame's fit, the shape again from the skin alone (.skin_shape):
    # body vertices within skin_distance of the clothed mesh are skin; the mask contours nearest
    # to them and the clothed mesh there fit pose and phenotypes, from several starts. Off by default:
    # a non-default body's rest shape 8.23 -> 3.73 mm, but on the demo excerpt's whole `run` the
    # preparation with it tracked 2.94 -> 3.51 mm and held-out CD 0.2056 -> 0.2225 (docs/prepare.md)
    skin_shape: bool = option(False, "fit the body's shape again from where the clothed mesh lies on it (arms, head, "
                                    "lower legs), so a shape other than Anny's default is found", flag="--skin-shape/--no-skin-shape")
    skin_distance: float = setting(0.008)  # [m]
    skin_starts: tuple = setting((-0.15, 0.0, 0.15))  # the pass's starts: age offsets at equal stature
    skin_sigma_factor: float = setting(2.0)  # the kernel narrows from sigma_end times this to sigma_end
    skin_iterations: int = setting(150)
    skin_step: float = setting(0.002)  # [m] Adam's step of the phenotypes, in rest-body displacement
    w_shape_prior_skin: float = setting(1e-5)
    w_skin_surface: float = setting(10.0)  # the skin on the clothed mesh, both sides (robust, kernel skin_distance)
    clothing_margin: float = setting(0.003)  # [m] the body keeps this far under the clothing
    bones: tuple = setting(FIT_BONES)
    seed: int = setting(0)


@dataclass
class BodyFit:
    """The fitted body, arrays exactly as ``body.npz`` holds them (docs/capture-format.md)."""

    shape: np.ndarray  # [6]
    bone_names: list[str]
    rotations: np.ndarray  # [T, B, 3]
    root_translation: np.ndarray  # [T, 3]
    topology: str
    report: dict = field(default_factory=dict)

    def body_poses(self):
        from ...capture import BodyPoses

        return BodyPoses(BodyShape.from_array(self.shape), self.bone_names, self.rotations, self.root_translation,
                         self.topology)

    def save(self, path: str | Path) -> None:
        self.body_poses().save(path)


def outside_weight(cfg: BodyFitConfig, sigma: float, keypoints: bool) -> float:
    """The outside term's weight at kernel ``sigma``: ``w_outside`` without keypoints; with them
    ``w_outside_keypoints``, reached from ``w_outside`` (geometrically) as the kernel narrows
    from 2 ``outside_ramp_sigma`` to ``outside_ramp_sigma``."""
    if not keypoints:
        return cfg.w_outside
    s0 = cfg.outside_ramp_sigma
    if s0 <= 0 or sigma <= s0:
        return cfg.w_outside_keypoints
    frac = min(np.log(sigma / s0) / np.log(2.0), 1.0)  # 0 at s0, 1 at 2 s0 and above
    return float(cfg.w_outside_keypoints * (cfg.w_outside / cfg.w_outside_keypoints) ** frac)


# -- optimisation --------------------------------------------------------------------------------

class _Fitter:
    def __init__(self, cfg: BodyFitConfig, obs: _Observations, clothing: ClothedSurface | None, fps: float,
                 fit_offsets: bool = False):
        self.cfg, self.obs, self.clothing, self.fps = cfg, obs, clothing, fps
        keypoints = obs is not None and obs.kp is not None
        self.offsets = None  # [C, 2] working px: each camera's image offset, fitted in the sequence pass
        self.kp_offsets = None  # [K, 3] each keypoint's landmark offset in the body's (root's) frame
        self.camera_offsets = None  # {camera: [du, dv]} the images' own px, once fitted
        self.fit_offsets = fit_offsets and cfg.fit_offsets and keypoints
        c = np.asarray(cfg.shape_centre, dtype=np.float64)
        if len(c) and (c.shape != (len(PHENOTYPES),) or not ((c >= 0) & (c <= 1)).all()):
            raise PhysavatarError(None, f"body fit: shape_centre must be {len(PHENOTYPES)} phenotypes in [0, 1] "
                                        f"({', '.join(PHENOTYPES)}), got {cfg.shape_centre}")
        self.model = _Model(cfg, curl=cfg.finger_curl and keypoints, thumbs=cfg.fit_thumbs and keypoints)
        self.A = self.model.n_params
        # the clothing terms (ICP-like, nearest clothed vertex) only once the pose is close:
        # from a far pose they squeeze the body into the wrong part of the clothing
        self.use_clothing = False
        self.skin = None  # [V] bool while the shape is fitted from the skin (.skin_shape), else None
        self.skin_samples = None  # [V + n F] the same for the silhouette samples
        # silhouette samples: the vertices and points spread over the triangles (about 1 cm
        # apart on the collider body), so a mask's edge always has a body point near it
        F_ = self.model.body.faces
        rng = np.random.default_rng(cfg.seed)
        n = cfg.samples_per_face
        bary = rng.dirichlet([1.0, 1.0, 1.0], size=(len(F_), n)).reshape(-1, 3)
        self.sample_faces = torch.as_tensor(np.repeat(F_, n, axis=0))
        self.sample_bary = torch.as_tensor(bary, dtype=DTYPE)
        self.kp_ids = np.array(self.model.kp_ids)
        # the spine bones' turns about the vertical (world-aligned axis-angle: the z component)
        self.twist_ids = [i for i, b in enumerate(self.model.bones) if b.startswith("spine")]
        # the clothed mesh's terms leave out the hands' and feet's extremities (fingers, metacarpals,
        # toes): a surface remeshed at a few centimetres has no fingers, only a blob whose nearest
        # vertex normals put the true fingers 3-4 cm "outside" it; they pulled the arms into the blob
        self.clothing_points = torch.as_tensor(np.flatnonzero(~_extremities(self.model.body)))

    def data_loss(self, frames: list[int], V, H, sigma: float, rot=None) -> torch.Tensor:
        cfg, obs = self.cfg, self.obs
        total = V.new_zeros(())
        kps = self.keypoints(V, H, rot) if obs.kp is not None else None
        for i, t in enumerate(frames):
            mesh = t == 0 and self.clothing is not None and self.use_clothing
            pressed = obs.kp is not None and (not mesh or len(obs.cams) < cfg.press_with_mesh_below)
            margin = cfg.outside_margin_px_keypoints if pressed else cfg.outside_margin_px
            o, c = silhouette_terms(self.samples(V[i]), obs.views(t), sigma, margin, self.offsets, self.skin_samples)
            w_out = outside_weight(cfg, sigma, True) if pressed else cfg.w_outside
            total = total + w_out * o + cfg.w_contour * c
            if kps is not None:
                conf = obs.conf[t][:, self.kp_ids] * self.model.kp_weight
                total = total + cfg.w_keypoints * keypoint_term(kps[i], obs.kp[t][:, self.kp_ids], conf, obs.cams,
                                                                max(sigma, cfg.kp_sigma), self.offsets)
            if mesh:
                total = total + self.clothing_loss(V[i], sigma)
        return total / len(frames)

    def keypoints(self, V, H, rot=None) -> torch.Tensor:
        """[T, K, 3] the model's keypoints, each moved by its landmark offset (in the body's frame,
        turned with the root: ``rot`` [T, A, 3]) once that is known."""
        kps = self.model.keypoints(V, H)
        if self.kp_offsets is None or rot is None:
            return kps
        R0 = axis_angle_to_matrix_t(rot[:, 0])  # [T, 3, 3]
        return kps + torch.einsum("tij,kj->tki", R0, self.kp_offsets)

    def outside_weight(self, sigma: float) -> float:
        return outside_weight(self.cfg, sigma, self.obs.kp is not None)

    def clothing_loss(self, V: torch.Tensor, sigma: float) -> torch.Tensor:
        """The clothed mesh's terms for body vertices ``V`` [V, 3] (the body inside the clothing,
        on it where it is skin), without the hands' and feet's extremities."""
        margin, near_on = self.cfg.clothing_margin, None
        if self.skin is not None:  # skin: on the clothed mesh, not under it
            near_on = self.skin[self.clothing_points]
            margin = torch.where(near_on, 0.0, margin)
        inside, near = self.clothing.terms(V[self.clothing_points], margin, sigma, near_on)
        loss = self.cfg.w_clothing_inside * inside + self.cfg.w_clothing_near * near
        if self.skin is not None:  # skin on the clothed mesh (both sides)
            d = self.clothing.signed_distance(V[self.skin])
            loss = loss + self.cfg.w_skin_surface * gm(d ** 2, self.cfg.skin_distance).mean()
        return loss

    def samples(self, V: torch.Tensor) -> torch.Tensor:
        """[V, 3] body vertices -> [V + n F, 3] vertices and surface samples."""
        P = (V[self.sample_faces] * self.sample_bary[:, :, None]).sum(1)
        return torch.cat([V, P])

    def prior(self, rot) -> torch.Tensor:
        p = self.cfg.w_pose_prior * (rot[:, 1:] ** 2).sum((1, 2)).mean()
        if self.cfg.w_spine_twist > 0 and self.twist_ids:
            # under a dress only the lower legs show the hips' heading: the pelvis turned ±20°
            # with the spine turning back (the shoulders right); a person's pelvis and chest turn together
            p = p + self.cfg.w_spine_twist * (rot[:, self.twist_ids, 2] ** 2).sum(1).mean()
        return p

    def shape_centre(self) -> torch.Tensor:
        c = self.cfg.shape_centre
        return torch.as_tensor(c, dtype=DTYPE) if len(c) else torch.full((len(PHENOTYPES),), 0.5, dtype=DTYPE)

    def shape_prior(self, phen) -> torch.Tensor:
        return self.cfg.w_shape_prior * ((phen - self.shape_centre()) ** 2).sum()

    def _run(self, params: list, lrs: list, iters: int, loss_fn, sigma0: float, sigma1: float, phen=None):
        cfg = self.cfg
        opt = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in zip(params, lrs)])
        last = None
        for it in range(iters):
            frac = it / max(iters - 1, 1)
            sigma = sigma0 * (sigma1 / sigma0) ** frac
            for g, lr in zip(opt.param_groups, lrs):
                g["lr"] = lr * (1.0 if frac < 0.7 else 0.2)
            opt.zero_grad()
            loss = loss_fn(sigma)
            loss.backward()
            opt.step()
            if phen is not None:
                body = self.model.body
                with torch.no_grad():  # trust region of the linearised shape, inside [0, 1]
                    lo, hi = (body.p0 - cfg.shape_step).clamp(min=0.0), (body.p0 + cfg.shape_step).clamp(max=1.0)
                    phen.copy_(torch.maximum(torch.minimum(phen, hi), lo))
                if (it + 1) % cfg.relinearize_every == 0 and it + 1 < iters:
                    body.relinearize(BodyShape.from_array(phen.detach().numpy()))
            last = float(loss.detach())
        return last

    # phase 1
    def first_frame(self, task) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        cfg, obs, body = self.cfg, self.obs, self.model.body
        views = obs.views(0)
        (cx, cy), zmin, zmax = _hull_extent(views)
        info = {"hull_height_m": round(zmax - zmin, 3)}
        phen = self.shape_centre()
        if len(cfg.shape_centre):
            body.relinearize(BodyShape.from_array(phen.numpy()))
        with torch.no_grad():
            v, _ = body.rest(phen)
        base = torch.as_tensor([cx - float(v[:, 0].mean()), cy - float(v[:, 1].mean()), zmin - float(v[:, 2].min())],
                               dtype=DTYPE)
        yaw = _heading_from_keypoints(obs.tri[0]) if obs.kp is not None else None
        candidates = [yaw] if yaw is not None else [0.0, 0.5 * np.pi, np.pi, -0.5 * np.pi]
        info["heading_from"] = "keypoints" if yaw is not None else "silhouettes (best of 4 headings)"

        def start(y):
            rot = torch.zeros(1, self.A, 3, dtype=DTYPE)
            rot[0, 0, 2] = y
            return rot.requires_grad_(), base.clone()[None].requires_grad_(), phen.clone().requires_grad_()

        def loss_fn(rot, tau, ph):
            def f(sigma):
                V, H = self.model.pose(rot, tau, ph)
                return self.data_loss([0], V, H, sigma, rot) + self.prior(rot) + self.shape_prior(ph)
            return f

        if len(candidates) > 1:
            scores = []
            for y in candidates:
                rot, tau, ph = start(y)
                scores.append((self._run([rot, tau, ph], [0.03, 0.01, 0.02], cfg.heading_iterations,
                                         loss_fn(rot, tau, ph), cfg.sigma_start, cfg.sigma_start, ph), y))
                task.advance()
            scores.sort()
            info["heading_losses"] = {f"{np.degrees(y):.0f}": round(s, 8) for s, y in scores}
            yaw = scores[0][1]
        info["heading_deg"] = round(float(np.degrees(yaw)), 1)
        rot, tau, ph = start(yaw)
        third = cfg.first_iterations // 3
        # pose first with the shape held (a wrong pose is not absorbed by a wrong shape), wide
        # kernel to narrow; then shape and pose together, re-linearising the shape after each part
        loss = self._run([rot, tau], [0.03, 0.01], third, loss_fn(rot, tau, ph), cfg.sigma_start, 2 * cfg.sigma_end)
        task.advance()
        self.use_clothing = True
        params, lrs = [rot, tau, ph], [0.02, 0.005, 0.02]
        if obs.kp is not None and self.clothing is not None and cfg.landmark_offsets:
            self.kp_offsets = torch.zeros(len(self.kp_ids), 3, dtype=DTYPE, requires_grad=True)
            params, lrs = params + [self.kp_offsets], lrs + [0.005]
        for s0, s1 in [(2 * cfg.sigma_end, cfg.sigma_end), (cfg.sigma_end, cfg.sigma_end)]:
            loss = self._run(params, lrs, third, loss_fn(rot, tau, ph), s0, s1, ph)
            body.relinearize(BodyShape.from_array(ph.detach().numpy()))
            task.advance()
        if self.kp_offsets is not None:
            self.kp_offsets = self.kp_offsets.detach()
            info["landmark_offsets_mm"] = {str(k): [round(1000 * float(x), 1) for x in o]
                                           for k, o in zip(self.kp_ids, self.kp_offsets)}
        info["first_frame_loss"] = loss
        if cfg.skin_shape and self.clothing is not None:
            from .skin_shape import skin_shape

            rot, tau, ph, skin_info = skin_shape(self, rot.detach(), tau.detach(), ph.detach())
            info["skin_shape"] = skin_info
        return rot.detach(), tau.detach(), ph.detach(), info

    # phase 2
    def frame(self, t: int, rots: list, taus: list, Hs: list, phen) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        cfg = self.cfg
        if t >= 2:
            r0 = 2 * rots[-1] - rots[-2]
            t0 = 2 * taus[-1] - taus[-2]
        else:
            r0, t0 = rots[-1].clone(), taus[-1].clone()
        rot, tau = r0.clone().requires_grad_(), t0.clone().requires_grad_()

        def f(sigma):
            V, H = self.model.pose(rot, tau, phen)
            loss = self.data_loss([t], V, H, sigma, rot) + self.prior(rot)
            if t >= 2:
                acc = H[0] - 2 * Hs[-1] + Hs[-2]
                # weak here: a constant-velocity prior would carry one frame's error into the next
                loss = loss + 0.1 * cfg.smoothness * (acc ** 2).sum(-1).mean()
            return loss

        self._run([rot, tau], [0.02, 0.005], cfg.frame_iterations, f, 0.5 * cfg.sigma_start, cfg.sigma_end)
        with torch.no_grad():
            _, H = self.model.pose(rot, tau, phen)
        return rot.detach(), tau.detach(), H[0]

    # phase 3
    def sequence(self, rot: torch.Tensor, tau: torch.Tensor, phen) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = self.cfg
        frames = list(range(rot.shape[0]))
        rot, tau = rot.clone().requires_grad_(), tau.clone().requires_grad_()

        def f(sigma):
            V, H = self.model.pose(rot, tau, phen)
            loss = self.data_loss(frames, V, H, sigma, rot) + self.prior(rot)
            if len(frames) >= 3:
                acc = H[2:] - 2 * H[1:-1] + H[:-2]
                loss = loss + cfg.smoothness * (acc ** 2).sum(-1).mean()
            return loss

        if not self.fit_offsets:
            self._run([rot, tau], [0.005, 0.002], cfg.sequence_iterations, f, cfg.sigma_end, cfg.sigma_end)
            return rot.detach(), tau.detach()
        # each camera's image offset with the body (calibration.py's from the keypoints carry the
        # detector's bias): held orthogonal to what a common shift of the body explains (the
        # translations are free), weakly drawn to 0; in metres at the body's distance
        cams = self.obs.cams
        with torch.no_grad():
            centre = self.model.pose(rot, tau, phen)[0].mean((0, 1)).numpy()
        from .calibration import _projection_jacobian

        Q = torch.as_tensor(np.linalg.qr(np.concatenate([_projection_jacobian(c, centre) for c in cams]))[0])
        m_px = torch.as_tensor([np.linalg.norm(c.center - centre) / c.K[0, 0] for c in cams], dtype=DTYPE)[:, None]
        self.offsets = torch.zeros(len(cams), 2, dtype=DTYPE, requires_grad=True)

        def g(sigma):
            d = self.offsets * m_px
            return f(sigma) + cfg.w_offset_gauge * ((Q.T @ d.reshape(-1)) ** 2).sum() + cfg.w_offset_prior * (d ** 2).sum()

        self._run([rot, tau, self.offsets], [0.005, 0.002, cfg.offset_lr], cfg.sequence_iterations, g, cfg.sigma_end,
                  cfg.sigma_end)
        off = self.offsets.detach().numpy().copy()
        self.offsets = None
        # the offsets go into the cameras (the check and the capture's cameras.json)
        from .calibration import shifted

        self.obs.cams = [shifted(c, o) for c, o in zip(cams, off)]
        for views in self.obs._views.values():
            for v, o in zip(views, off):
                v.camera = shifted(v.camera, o)
        self.camera_offsets = {n.name: [round(float(x) * n.width / c.width, 3) for x in o]
                               for n, c, o in zip(self.obs.native, cams, off)}
        return rot.detach(), tau.detach()


# -- entry point ---------------------------------------------------------------------------------

def fit_body(capture_dir: str | Path, *, template_vertices: np.ndarray | None, config: BodyFitConfig | None = None,
             progress=None, template_faces: np.ndarray | None = None, fit_offsets: bool = False) -> BodyFit:
    """Fit the Anny body to every frame of a capture (see the module doc).

    Args:
        capture_dir: a capture folder with cameras, frames and masks (images when a keypoint
            detector is used).
        template_vertices: [V, 3] the first frame's clothed mesh (or None); ``template_faces``
            [F, 3] its triangles when known (better normals for the inside test).
        config: :class:`BodyFitConfig`.
    Returns:
        :class:`BodyFit`, arrays as body.npz holds them, and a report (``report``).
    """
    cfg = config or BodyFitConfig()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small tensors: one thread is faster, and far faster on a busy machine
    try:
        return _fit(Path(capture_dir), template_vertices, template_faces, cfg, progress, fit_offsets)
    finally:
        torch.set_num_threads(threads)


def _fit(root: Path, template_vertices, template_faces, cfg: BodyFitConfig, progress, fit_offsets=False) -> BodyFit:
    from ...progress import resolve

    t0 = time.time()
    torch.manual_seed(cfg.seed)
    prog = resolve(progress)
    obs = _Observations(root, cfg, prog)
    meta = read_json(root / "capture.json")
    fps = float(meta.get("fps", 25.0))
    if len(obs.frames) >= 2:  # frames kept every n-th (import --every n): n source frames apart
        fps /= max(float(np.median(np.diff(np.asarray(obs.frames, np.float64)))), 1.0)
    clothing = None
    if template_vertices is not None:
        tv = np.asarray(template_vertices, dtype=np.float64)
        if tv.ndim != 2 or tv.shape[1] != 3 or not np.isfinite(tv).all():
            raise PhysavatarError(None, f"body fit: template vertices must be finite [V, 3], got {tv.shape}")
        clothing = ClothedSurface(tv, template_faces)
    fitter = _Fitter(cfg, obs, clothing, fps, fit_offsets)
    T = len(obs.frames)
    report: dict = {"detector": obs.detector_note, "frames": T, "cameras": len(obs.cams),
                    "working_resolution": [[c.width, c.height] for c in obs.cams][:1][0]}
    with torch.set_grad_enabled(True):
        with prog.task("prepare: body, first frame", total=(0 if obs.kp is not None else 4) + 3) as task:
            rot0, tau0, phen, info = fitter.first_frame(task)
        report.update(info)
        t1 = time.time()
        rots, taus = [rot0], [tau0]
        with torch.no_grad():
            _, H0 = fitter.model.pose(rot0, tau0, phen)
        Hs = [H0[0]]
        with prog.task("prepare: body, per frame", total=T - 1) as task:
            for t in range(1, T):
                r, tr, H = fitter.frame(t, rots, taus, Hs, phen)
                rots.append(r)
                taus.append(tr)
                Hs.append(H)
                task.advance(frame=obs.frames[t])
        rot, tau = torch.cat(rots), torch.cat(taus)
        t2 = time.time()
        if T >= 3 and cfg.sequence_iterations > 0:
            with prog.task("prepare: body, whole sequence", total=1) as task:
                rot, tau = fitter.sequence(rot, tau, phen)
                task.advance()
    report.update(check(fitter, rot, tau, phen))
    if fitter.camera_offsets:
        report["camera_offsets_px"] = fitter.camera_offsets  # the images' own pixels
    shape = BodyShape.from_array(np.clip(phen.numpy(), 0.0, 1.0))
    report["shape"] = shape.to_dict()
    with torch.no_grad():
        R = fitter.model.full_rotations(rot).numpy()
    trans = tau.numpy() - np.array([0.0, 0.0, DiffBody.floor_offset(shape)])
    elapsed = time.time() - t0
    report["seconds"] = {"total": round(elapsed, 1), "first_frame": round(t1 - t0, 1),
                         "per_frame": round((t2 - t1) / max(T - 1, 1), 2),
                         "sequence": round(time.time() - t2, 1), "per_frame_overall": round(elapsed / T, 2)}
    return BodyFit(shape.as_array(), list(fitter.model.body.bone_names), R, trans, cfg.topology, report)


__all__ = ["FIT_BONES", "PHENOTYPES", "BodyFit", "BodyFitConfig", "fit_body"]
