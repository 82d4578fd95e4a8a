"""Mesh tracking with mesh-aligned Gaussians (PhysAvatar Sec. 3.1), on a CPU.

One flat Gaussian sits on each template face (:func:`physavatar.splat.mesh_to_gaussians`); it
carries a colour (linear RGB, composited in linear light and then sRGB-encoded, like the
renderer that made the capture), two in-plane log-scales and an opacity logit.

- Frame 1 (the template is frame 1): colours, scales and opacities are fitted, vertices fixed.
- Frames t > 1 (``init="mixed"``): the body and the garment's boundary start on the template
  skinned to the capture's body pose of frame t, the free garment on its own constant-velocity
  prediction (:func:`mixed_prediction`); the vertices are fitted, colours, scales and opacities
  stay as frame 1 left them (by default). The loss is Eq. 4 plus an anchor of the skinned
  vertices to their pose,

      L = λ L1 + (1 - λ)(1 - SSIM)  +  w_mask |alpha - mask|  +  λ_iso L_iso  +  λ_n L_normal
          + w_anchor L_anchor  +  w_coll L_collision,

  rendered into every training camera at every step, coarse to fine over an image pyramid, with
  Adam and early stopping on a loss plateau (docs/tracking.md gives the schedule and why).

Outputs (``track(capture, out, config)``)::

    out/config.json            the exact TrackConfig (holdout resolved to camera names)
    out/frames/<frame>.npz     vertices [V, 3] float32, face_colors [F, 3] (linear RGB);
                               the first frame also log_scales [F, 2], opacity_logits [F], edge_index [F]
    out/meshes/<frame>.ply     the tracked mesh with per-vertex label and boundary
    out/track_log.csv          frame, iterations, final loss terms, seconds
    out/tracked.npz            vertices [T, V, 3], faces, labels, face_colors [T, F, 3], frames, ...

Every file is written atomically; a rerun with the same config skips finished frames.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..camera import Camera
from ..capture import Capture, frame_name, load_capture
from ..data.tracked import FILE as TRACKED, TrackedSequence
from ..errors import PhysavatarError
from ..files import PlyMesh, load_npz, read_json, save_npz_atomic, write_json_atomic, write_ply, write_text_atomic
from ..geometry import mesh_edges
from ..optim.uniform import AdamUniform
from ..render.image import srgb_to_linear
from ..splat import longest_edge_index, mesh_to_gaussians, rasterize
from .flow import to_gray8
from ._losses import AnchorLoss, CollisionLoss, IsometryLoss, NormalLoss, linear_to_srgb, ssim

LOG_COLUMNS = ("frame", "iterations", "loss", "render", "l1", "ssim", "mask", "iso", "normal", "anchor", "collision", "seconds")


@dataclass(frozen=True)
class TrackConfig:
    """Everything that defines a tracking run (saved as config.json).

    Attributes:
        holdout: camera names excluded from fitting; None = the default rule
            (:func:`default_holdout`: two cameras when the capture has at least six).
        n_frames: track only the first N frames (None: all). Not part of the resume check, so a
            run can be extended.
        scale: resolution factor of the finest pyramid level w.r.t. the capture's images.
        levels: pyramid levels as fractions of ``scale``, coarse to fine.
        iters_first, iters: maximum iterations per level for frame 1 and for later frames.
        min_iters, check_every, plateau_tol: a level stops early once the mean loss of the last
            ``check_every`` steps improved on the window before by less than ``plateau_tol``
            (relative), after at least ``min_iters`` steps.
        l1_weight: λ of Eq. 1 (0.8 as the official code: 0.8 L1 + 0.2 (1 - SSIM)).
        mask_weight: weight of |rendered alpha - mask| (0 ignores the masks) on frame 1;
            mask_weight_track on later frames (with colours fixed the silhouette is the part of
            the image the frame-1 appearance model gets right; measured in docs/tracking.md).
        iso_weight, normal_weight: λ_iso, λ_n of Eq. 4 (0 for the ablation).
        normal_mode: "paper" (Eq. 3 as printed) or "rest" (change of each dihedral since frame
            1; see :class:`NormalLoss`).
        lr_vertices: Adam step size of the vertices at the finest level [m]; a level whose
            pixels are k times larger uses k times this.
        lr_decay: every level's step sizes decay exponentially to this fraction at its last step.
        lr_colors, lr_scales, lr_opacity: Adam step sizes on frame 1 (linear RGB, log-scale,
            logit). Scales and opacities stay fixed by default (0): per-face scales and
            opacities fitted to frame 1's silhouettes (opacities spread 0.04-0.98) do not transfer
            to the faces that make the silhouette later (docs/tracking.md).
        velocity: factor of the constant-velocity term of each frame's prediction (0: none).
        velocity_smoothing: λ of a (I + λ L)^-1 low-pass of that velocity under ``init="mixed"``
            (0: the raw difference of the last two tracked frames).
        init: how frame t starts. "mixed" (default, :func:`mixed_prediction`): body and garment
            boundary skinned to the body pose of frame t, the rest of the garment
            x_{t-1} + velocity (x_{t-1} - x_{t-2}). "lbs": the template skinned to the capture's body pose of
            frame t (body.npz, the body model's LBS; garment weights transferred from the
            closest body point), plus the previous frames' tracked residual from that skinning,
            carried in each vertex's local skinning frame and extrapolated with ``velocity``
            (:class:`TemplateSkinning`). "velocity": v_{t-1} + velocity (v_{t-1} - v_{t-2}).
        target_blur: Gaussian blur (px) of the target images and masks at each level, meant to
            match the splats' 0.3 px² low-pass (0: off; 0.5 px did not reduce the frame-1 refit
            bias on the tiny capture, docs/tracking.md).
        lr_colors_track: colour step size on frames t > 1 (default 0: fixed after frame 1).
            Colours that chase every frame's image absorb misalignment instead of exposing it to
            the vertices.
        subdivide: midpoint subdivisions of the template for the Gaussians (4^k splats per face,
            attached at fixed barycentric positions, so gradients still reach the template
            vertices). One flat colour per coarse face cannot show texture finer than the mesh.
        body_residual, garment_residual: the share of the body's / garment's tracked residual
            from skinning carried to the next frame with ``init="lbs"``. Below one, the start of
            each frame leans back toward the skinned pose, which bounds the drift: a per-frame
            fitting error b adds up to b / (1 - share) instead of growing without end
            (docs/tracking.md, measured).
        vertex_optimizer: "uniform" (:class:`AdamUniform`: one second-moment normaliser for all
            vertices) or "adam" (per-coordinate Adam). uniform_quantile: its normaliser's quantile.
        smoothing: λ of the vertex update's smoothing (I + λ L)^-1 (:class:`SmoothedSolve`);
            0 optimizes the vertices directly.
        threads: numba and torch threads during the fit (1 is fastest on a shared 2-core machine:
            the per-view work at these image sizes is too small to pay for thread start-up).
        seed: torch seed (the fit itself uses no randomness; kept for reproducibility).
        collision_weight, collision_margin: garment-body penalty (:class:`CollisionLoss`, the
            official code has one) and its margin [m]; 0 = off (default: once the rendering's
            silhouette bias is gone it only pushed penetrated cloth out on the wrong side; demo,
            frames 2-8: worst frame 16 -> 11 mm without it).
        antialiased: render with the mass-conserving low-pass (:func:`physavatar.splat.rasterize`).
            The plain 3DGS low-pass widens the silhouette of a surface of sub-pixel splats (demo,
            128²: +20 % of the mask) and the fit shrinks the garment to undo it.
        opacity: every splat's opacity (fixed unless lr_opacity > 0): an opaque surface.
        anchor_weight: weight of :class:`AnchorLoss` (1 cm units) holding the body and the
            garment boundary near their skinned pose under ``init="mixed"``: the capture's body
            poses place the body better than the images do (measured: free, the fit moved the
            exactly-placed demo body 3-6 mm; anchored, 0.4-0.5 mm).
        garment_prediction: how the free garment starts under ``init="mixed"``: "velocity"
            (x_{t-1} + velocity S(x_{t-1} - x_{t-2}), :func:`mixed_prediction`) or "physics" (one
            implicit-Euler step of the cloth simulator from the last two tracked frames with that
            velocity, the body skinned to frames t-1 and t as collider: :class:`PhysicsPrediction`;
            frames whose tracked garment intersects the body fall back to "velocity"), or "flow"
            (:mod:`physavatar.stages.flow`: the multi-view optical flow I_{t-1} -> I_t of the
            training cameras at full resolution lifted to the garment vertices, then
            ``flow_corrections`` model-based corrections against the first frame's projective
            texture; docs/tracking.md).
        flow_smoothness: membrane smoothness of the flow lift (dimensionless, see
            :class:`~physavatar.stages.flow.FlowPrediction`).
        flow_corrections: model-based flow corrections per frame under "flow" (0: prediction only).
        flow_iso: weight of the edge-length term of the flow lift, toward the template's lengths
            (the hem seen by one or two cameras is otherwise free to stretch along the rays).
        flow_bend: weight of the bending term of the flow lift (distances across the garment's
            interior edges toward the template's: its folds' dihedral angles), so a fold cannot
            slide along itself where the edge lengths alone allow it (sixth session; demo, late
            frames: docs/tracking.md).
        flow_collision: penalty weight holding the free garment outside the body in every flow lift
            (0: off); without it the chain pushed 10 % of the demo dress into the legs by frame 14.
        flow_final_corrections: model-based corrections after the photometric fit (the fit's own
            optimum at 128² lies 1-2 mm from a corrected start; demo, docs/tracking.md).
        flow_correction_smoothness, flow_correction_prior, flow_correction_iso, flow_correction_bend: the corrections'
            lift: membrane smoothness, pull toward the estimate, edge-length term (measured on the
            demo from saved prediction states of frames 16, 33, 46: 0.1 / 0.01 / 10 against the
            fourth session's 1 / 0.1 / 3 took two corrections from 4.0 / 6.2 / 6.0 mm to 3.1 / 4.3 / 5.1).
        prediction_material: simulator material preset of the physics prediction (the garment's
            material is not known when tracking: a prior; on the demo a wrong one, silk for the
            cotton dress, made the start 3-4x worse than constant velocity, docs/tracking.md).
        prediction_newton_iterations: cap on that step's Newton iterations. A converged step took
            19-37 on the demo dress (7-17 s); capped at 4 it stays in the phase where the body
            sweeps into the cloth and is worse than constant velocity.
        level_iters: maximum iterations of frames t > 1 per pyramid level (coarse to fine);
            None: ``iters`` on every level.
    """

    holdout: tuple[str, ...] | None = None
    n_frames: int | None = None
    scale: float = 0.25
    levels: tuple[float, ...] = (0.5, 1.0)
    iters_first: int = 150
    iters: int = 15
    min_iters: int = 20
    check_every: int = 10
    plateau_tol: float = 2e-3
    l1_weight: float = 0.8
    mask_weight: float = 0.5
    mask_weight_track: float = 1.0
    iso_weight: float = 20.0
    normal_weight: float = 0.1
    normal_mode: str = "rest"
    lr_vertices: float = 4e-3
    lr_decay: float = 0.1
    lr_colors: float = 0.01
    lr_scales: float = 0.0
    lr_opacity: float = 0.0
    velocity: float = 1.0
    velocity_smoothing: float = 30.0
    init: str = "mixed"
    vertex_optimizer: str = "uniform"
    uniform_quantile: float = 0.5
    body_residual: float = 0.0
    garment_residual: float = 0.5
    target_blur: float = 0.0
    lr_colors_track: float = 0.0
    subdivide: int = 0
    smoothing: float = 10.0
    threads: int = 1
    seed: int = 0
    collision_weight: float = 0.0
    collision_margin: float = 0.001
    anchor_weight: float = 1.0
    antialiased: bool = True
    opacity: float = 0.99
    garment_prediction: str = "flow"
    prediction_material: str = "cotton"
    prediction_newton_iterations: int = 40
    level_iters: tuple[int, ...] | None = None
    flow_smoothness: float = 3.0
    flow_corrections: int = 3
    flow_iso: float = 3.0
    flow_bend: float = 10.0
    flow_collision: float = 1e3
    flow_final_corrections: int = 1
    flow_correction_smoothness: float = 0.1
    flow_correction_prior: float = 0.01
    flow_correction_iso: float = 10.0
    flow_correction_bend: float = 5.0

    def to_json(self) -> dict:
        d = asdict(self)
        d["holdout"] = None if self.holdout is None else list(self.holdout)
        d["levels"] = list(self.levels)
        d["level_iters"] = None if self.level_iters is None else list(self.level_iters)
        return d

    @staticmethod
    def from_json(d: dict) -> "TrackConfig":
        names = {f.name for f in fields(TrackConfig)}
        d = {k: v for k, v in d.items() if k in names}
        if d.get("holdout") is not None:
            d["holdout"] = tuple(d["holdout"])
        if "levels" in d:
            d["levels"] = tuple(d["levels"])
        if d.get("level_iters") is not None:
            d["level_iters"] = tuple(d["level_iters"])
        return TrackConfig(**d)


def default_holdout(camera_names: list[str]) -> tuple[str, ...]:
    """Two held-out cameras (as the paper), half a rig apart: positions 1 and 1 + C/2 in the
    capture's order. Captures with fewer than six cameras keep every view for fitting."""
    C = len(camera_names)
    if C < 6:
        return ()
    return (camera_names[1], camera_names[1 + C // 2])


# -- the Gaussians -------------------------------------------------------------------------------

@dataclass
class MeshGaussians:
    """Per-face Gaussian parameters of a template (the vertices live outside).

    Attributes:
        faces: [F, 3] long. edge_index: [F] the face frames' x edge (longest edge of frame 1).
        colors: [F, 3] linear RGB. log_scales: [F, 2]. opacity_logits: [F].
    """

    faces: torch.Tensor
    edge_index: torch.Tensor
    colors: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    midpoints: list = field(default_factory=list)  # per subdivision level: [E, 2] edge endpoints
    antialiased: bool = False  # mass-conserving low-pass (:func:`physavatar.splat.rasterize`)

    @staticmethod
    def init(vertices: np.ndarray, faces: np.ndarray, subdivide: int = 0, opacity: float = 0.88,
             antialiased: bool = False) -> "MeshGaussians":
        """Gaussians of ``faces``, or of their ``subdivide``-times midpoint subdivision (4^k per face),
        all with opacity ``opacity``."""
        faces = np.asarray(faces, np.int64)
        mids = []
        for _ in range(subdivide):
            faces, m = _midpoint_subdivide(faces, len(vertices) + sum(len(x) for x in mids))
            mids.append(m)
        model = MeshGaussians(torch.from_numpy(faces), torch.zeros(0), torch.zeros(0), torch.zeros(0), torch.zeros(0),
                              [torch.from_numpy(m) for m in mids], antialiased)
        V = model.gaussian_vertices(torch.from_numpy(np.asarray(vertices, np.float32)))
        tri = V[model.faces]
        area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)
        # sigma = 0.45 sqrt(area) is 0.3 of an equilateral face's side: neighbouring splats
        # overlap enough to close the surface without bleeding far past the face.
        s = (0.45 * area.clamp(min=1e-12).sqrt()).log()
        model.edge_index = longest_edge_index(V, model.faces)
        model.colors = torch.full((len(model.faces), 3), 0.2)
        model.log_scales = torch.stack([s, s], dim=1)
        model.opacity_logits = torch.full((len(model.faces),), float(np.log(opacity / (1.0 - opacity))))
        return model

    def gaussian_vertices(self, vertices: torch.Tensor) -> torch.Tensor:
        """[V', 3] the vertices of the (subdivided) Gaussian mesh: linear in ``vertices``."""
        for m in self.midpoints:
            vertices = torch.cat([vertices, 0.5 * (vertices[m[:, 0]] + vertices[m[:, 1]])])
        return vertices

    def face_colors(self, n_faces: int) -> np.ndarray:
        """[F, 3] per template face: the mean colour of its 4^k sub-faces (subdivision keeps
        each face's children contiguous)."""
        c = self.colors.numpy()
        return c.reshape(n_faces, -1, 3).mean(1).astype(np.float32)

    def splats(self, vertices: torch.Tensor, colors: torch.Tensor | None = None,
               log_scales: torch.Tensor | None = None, opacity_logits: torch.Tensor | None = None) -> tuple:
        """(means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colors [N, 3]) of the
        Gaussians on ``vertices`` [V, 3]; computed once per step and shared by every view
        (building them per view multiplied the autograd graph by the number of cameras)."""
        means, quats, scales = mesh_to_gaussians(
            self.gaussian_vertices(vertices), self.faces, self.log_scales if log_scales is None else log_scales, self.edge_index)
        col = (self.colors if colors is None else colors).clamp(0.0, 1.0)
        op = torch.sigmoid(self.opacity_logits if opacity_logits is None else opacity_logits)
        return means, quats, scales, op, col

    def rasterize(self, splats: tuple, cam: Camera) -> dict:
        """Rasterize :meth:`splats` into ``cam``: rgb [H, W, 3] linear (over black), alpha [H, W]."""
        return rasterize(*splats, torch.from_numpy(cam.w2c.astype(np.float32)), torch.from_numpy(cam.K.astype(np.float32)),
                         cam.width, cam.height, backend="numba", antialiased=self.antialiased)

    def render(self, vertices: torch.Tensor, cam: Camera, colors: torch.Tensor | None = None,
               log_scales: torch.Tensor | None = None, opacity_logits: torch.Tensor | None = None) -> dict:
        """Rasterize into ``cam``: rgb [H, W, 3] linear (over black), alpha [H, W]."""
        return self.rasterize(self.splats(vertices, colors, log_scales, opacity_logits), cam)


def _midpoint_subdivide(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Split each triangle into four at its edge midpoints.

    Returns the new faces [4F, 3] (face f's children at rows 4f..4f+3) and the midpoints' edge
    endpoints [E, 2]; midpoint e gets vertex index n_vertices + e.
    """
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    uniq, inv = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True)
    inv = inv.reshape(3, -1).T + n_vertices  # [F, 3] midpoint of edge (0,1), (1,2), (2,0)
    a, b, c = faces.T
    ab, bc, ca = inv.T
    new = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                    np.stack([ab, bc, ca], 1)], 1).reshape(-1, 3)
    return new, uniq


# -- views ---------------------------------------------------------------------------------------

@dataclass
class View:
    """One camera at one pyramid level: camera, image [H, W, 3] sRGB, mask [H, W]."""

    camera: Camera
    image: torch.Tensor
    mask: torch.Tensor


def _resize(a: np.ndarray, w: int, h: int) -> np.ndarray:
    if a.shape[1] == w and a.shape[0] == h:
        return a
    # box filter = the area average of each coarse pixel, the image a coarse camera would see
    if a.ndim == 2:
        return np.asarray(Image.fromarray(a.astype(np.float32), mode="F").resize((w, h), Image.BOX))
    return np.stack([_resize(a[..., c], w, h) for c in range(a.shape[2])], -1)


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return a
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(a, (sigma, sigma) + (0,) * (a.ndim - 2), mode="nearest")


def load_views(capture: Capture, frame: int, cameras: list[Camera], factor: float, blur: float = 0.0,
               images: list[np.ndarray] | None = None) -> list[View]:
    """Every camera's image and mask box-filtered to ``factor`` of the capture's size, then
    blurred with a Gaussian of ``blur`` px (see TrackConfig.target_blur). ``images``: the
    cameras' full-resolution images of ``frame`` when already read."""
    out = []
    for k, cam in enumerate(cameras):
        c = cam.scaled(factor) if factor != 1.0 else cam
        full = capture.image(cam.name, frame) if images is None else images[k]
        img = _blur(_resize(full, c.width, c.height), blur)
        msk = _blur(_resize(capture.mask(cam.name, frame), c.width, c.height), blur)
        out.append(View(c, torch.from_numpy(np.array(img, np.float32)),
                        torch.from_numpy(np.array(msk, np.float32))))
    return out


def initial_colors(vertices: np.ndarray, faces: np.ndarray, views: list[View]) -> np.ndarray:
    """[F, 3] linear RGB: per face, the median over cameras of the pixel under its barycentre
    (inside the mask). Occlusion is ignored — the fit corrects the few wrong faces; this only
    saves the colours most of their way from grey."""
    bary = vertices[faces].mean(1)
    samples = []
    for v in views:
        uv, z = v.camera.project(bary)
        u = np.rint(uv[:, 0]).astype(int)
        w = np.rint(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < v.camera.width) & (w >= 0) & (w < v.camera.height)
        s = np.full((len(faces), 3), np.nan)
        m = v.mask.numpy()
        ok[ok] &= m[w[ok], u[ok]] > 0.5
        s[ok] = v.image.numpy()[w[ok], u[ok]]
        samples.append(s)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(np.stack(samples), axis=0)
    med = np.where(np.isfinite(med), med, 0.5)
    return srgb_to_linear(med).astype(np.float32)


class SmoothedSolve(torch.autograd.Function):
    """x = M^-1 u for the fixed SPD matrix M = I + λ L (L the graph Laplacian of the mesh).

    The "large steps" reparametrization (Nicolet et al. 2021): Adam updates u, and the vertices
    move by M^-1 of it, a smooth field. Photometric gradients per vertex are noisy (each sees a
    few pixels of texture); through M^-1 they act on whole neighbourhoods, so a limb that moved
    several pixels between frames is followed in tens of steps instead of being torn apart.
    M's rows sum to one (L 1 = 0): a uniform shift of u is the same shift of x, so step sizes
    keep their meaning in metres. M is symmetric, so the backward pass is the same solve.
    """

    @staticmethod
    def forward(ctx, u, solve):
        ctx.solve = solve
        return torch.from_numpy(solve(u.detach().double().numpy())).to(u.dtype)

    @staticmethod
    def backward(ctx, g):
        return torch.from_numpy(ctx.solve(g.double().numpy())).to(g.dtype), None


def smoothing_solver(n_vertices: int, faces: np.ndarray, lam: float):
    """A function [V, 3] -> [V, 3] applying (I + lam L)^-1 (sparse LU, factorized once)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    e = mesh_edges(np.asarray(faces))
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    A = (A + A.T).tocsr()
    L = sp.diags(np.asarray(A.sum(1)).ravel()) - A
    lu = splu((sp.identity(n_vertices) + lam * L).tocsc())
    return lambda b: lu.solve(np.ascontiguousarray(b))


class TemplateSkinning:
    """Linear blend skinning of the template by the capture's body poses (the initialization of
    each frame; the paper also drives its template with the fitted body's LBS).

    The body part of the template is the body model's mesh (its own skinning weights when the
    vertex counts and positions agree); every other vertex takes the weights of its closest body
    point (:func:`physavatar.garment.garment_skinning_weights`). Transforms are relative to the
    first frame, whose pose the template is in, so a template that is not in the rest pose works
    too: A_b(t) = T_b(t) T_b(1)^-1.

    Attributes:
        weights: [V, B]. transforms: [T, B, 4, 4] for every frame of the capture.
    """

    def __init__(self, template_vertices: np.ndarray, weights: np.ndarray, transforms: np.ndarray,
                 carry: np.ndarray | None = None):
        self.template = np.asarray(template_vertices, np.float64)
        # [V] how much of its tracked residual each vertex carries to the next frame
        self.carry = np.ones(len(self.template)) if carry is None else np.asarray(carry, np.float64)
        self.weights = np.asarray(weights, np.float64)
        self.transforms = np.asarray(transforms, np.float64)

    @staticmethod
    def from_capture(cap: Capture, body_residual: float = 1.0, garment_residual: float = 1.0) -> "TemplateSkinning":
        from types import SimpleNamespace

        from ..body import BodyModel
        from ..garment import garment_skinning_weights

        t = cap.template
        body = BodyModel(cap.body.shape, topology=cap.body.topology)
        posed = body.pose(cap.body.rotations, cap.body.root_translation)
        Tb = posed.bone_transforms
        rel = Tb @ np.linalg.inv(Tb[0])[None]
        V = np.asarray(t.vertices, np.float64)
        body_idx = np.flatnonzero(~t.garment_mask)
        W = np.zeros((len(V), Tb.shape[1]))
        first = posed.vertices[0]
        if len(body_idx) == len(first) and np.abs(V[body_idx] - first).max() < 1e-3:
            W[body_idx] = body.skinning_weights
            other = np.flatnonzero(t.garment_mask)
        else:  # the template's body is not this body model's mesh: transfer to every vertex
            other = np.arange(len(V))
        if len(other):
            # closest point on the body of frame 1 (the template's pose), not on the rest body
            at_first = SimpleNamespace(rest_vertices=first, faces=body.faces, skinning_weights=body.skinning_weights)
            W[other] = garment_skinning_weights(V[other], at_first)
        carry = np.where(t.garment_mask, garment_residual, body_residual)
        return TemplateSkinning(V, W, rel, carry)

    def matrices(self, index: int) -> np.ndarray:
        """[V, 3, 4] each vertex's blended transform from frame 1 to capture frame ``index``."""
        return np.einsum("vb,bij->vij", self.weights, self.transforms[index, :, :3, :])

    def skin(self, index: int, points: np.ndarray | None = None) -> np.ndarray:
        """[V, 3] ``points`` (default: the template) moved by frame ``index``'s blended transforms."""
        A = self.matrices(index)
        P = self.template if points is None else points
        return np.einsum("vij,vj->vi", A[..., :3], P) + A[..., 3]

    def unskin(self, index: int, points: np.ndarray) -> np.ndarray:
        """[V, 3] the inverse of :meth:`skin`: ``points`` of frame ``index`` in the template's pose."""
        A = self.matrices(index)
        return np.linalg.solve(A[..., :3], (np.asarray(points, np.float64) - A[..., 3])[..., None])[..., 0]

    def predict(self, index: int, tracked: list[np.ndarray], velocity: float) -> np.ndarray:
        """[V, 3] float32 start of capture frame number ``index`` (position in the capture) from
        ``tracked``, the vertices of the frames before it (``tracked[-1]`` is frame index - 1).

        The residual r = unskin(x) - template (what skinning does not explain: cloth lag, folds)
        changes slowly, so it is carried over in each vertex's local frame and extrapolated:
        x_t = skin_t(template + r_{t-1} + velocity (r_{t-1} - r_{t-2})). Body vertices carry
        ``body_residual`` of theirs (default 0: the body starts on the capture's body pose of
        frame t, which drives it; carrying its residual only accumulated each frame's photometric
        error — measured on the demo capture: a 1-2 mm shift per frame that added up).
        """
        k = self.carry[:, None]
        r1 = k * (self.unskin(index - 1, tracked[-1]) - self.template)
        c = self.template + r1
        if velocity and len(tracked) >= 2:
            r2 = k * (self.unskin(index - 2, tracked[-2]) - self.template)
            c = c + velocity * (r1 - r2)
        return self.skin(index, c).astype(np.float32)


def mixed_prediction(skin: TemplateSkinning, index: int, tracked: list[np.ndarray], velocity: float,
                     skinned: np.ndarray, smooth=None) -> np.ndarray:
    """[V, 3] float32 start of capture frame ``index`` under ``init="mixed"``.

    Vertices flagged in ``skinned`` [V] (the body and the garment's boundary) take the template
    skinned to the body pose of frame ``index``; the free garment continues its own motion,
    x_{t-1} + velocity (x_{t-1} - x_{t-2}). A simulated garment does not follow skinning: on the
    demo dress, skinning alone is 90-140 mm off (the legs drag the skirt), while the constant-
    velocity prediction from the true previous frames is 3-11 mm off (docs/tracking.md).
    """
    prev = tracked[-1].astype(np.float64)
    x = prev.copy()
    if len(tracked) >= 2:
        v = prev - tracked[-2]
        # ``smooth`` (a low-pass over the mesh): each frame's fitting noise is rough, the cloth's
        # motion smooth; extrapolating the raw difference doubles the noise every frame
        x += velocity * (smooth(v) if smooth is not None else v)
    x[skinned] = skin.skin(index)[skinned]
    return x.astype(np.float32)


class PhysicsPrediction:
    """The garment's start for frame t from one cloth-simulator step (paper Sec. 3.2's simulator,
    :mod:`physavatar.sim`), under ``garment_prediction="physics"``.

    The garment at t-1 with velocity v = (x_{t-1} - x_{t-2}) / h (optionally low-passed) takes one
    implicit-Euler step of length h = 1/fps against the body moving from its pose at t-1 to t;
    its boundary vertices follow the body point they sit on in the template (as
    :func:`physavatar.garment_sim.simulate_on_body`, which made the demo's ground truth). Constant
    velocity keeps a swinging hem going straight; the step adds gravity, the membrane's pull
    back towards its rest lengths and the body's push.

    Args:
        vertices [V, 3], faces [F, 3], labels [V] (> 0 garment), boundary [V] bool: the template;
            its garment is the rest shape, its body part (label 0) the collider's topology.
        material: :class:`physavatar.sim.Material` (a prior: the real one is not known yet).
        fps: the capture's frame rate. settings: :class:`physavatar.sim.SimSettings` (dt is
            replaced by 1/fps).
        push_clearance: a tracked garment that intersects the body at t-1 is first pushed out
            to this distance [m] (:func:`physavatar.garment.garment.push_out`); if it still
            intersects, there is no prediction (None).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, boundary: np.ndarray,
                 material, fps: float, settings=None, push_clearance: float = 1e-3):
        from ..garment.garment import make_attachment
        from ..garment_sim import split_template
        from ..sim import ClothSim, SimSettings
        from ..sim.contact import ContactScene

        V = np.asarray(vertices, np.float64)
        self.body_ids, self.body_faces, part = split_template(V, np.asarray(faces), np.asarray(labels),
                                                              np.asarray(boundary, bool))
        self.garment_ids = part.vertex_ids
        self.boundary = part.boundary
        self.h = 1.0 / fps
        settings = replace(settings or SimSettings(), dt=self.h)
        self.sim = ClothSim(part.vertices, part.faces, material, settings, part.boundary)
        self.attachment = make_attachment(part.vertices[part.boundary], part.boundary, V[self.body_ids],
                                          self.body_faces, "sequence")
        # the intersection test of the start state (ipctk's CCD assumes an intersection-free start)
        self._scene = ContactScene(part.vertices, part.faces, V[self.body_ids], self.body_faces, settings.dhat)
        self._faces = part.faces
        self.push_clearance = push_clearance
        self.last_stats = None
        self.pushed = False

    def __call__(self, prev2: np.ndarray, prev: np.ndarray, body_prev: np.ndarray, body_next: np.ndarray,
                 velocity: float = 1.0, smooth=None) -> np.ndarray | None:
        """[V, 3] float64: ``prev`` with the garment stepped to frame t (the body part is copied
        from ``body_next``), or None when the garment of ``prev`` intersects ``body_prev`` even
        after pushing it out (``self.pushed`` says whether it was pushed).

        prev2, prev: [V, 3] the template's vertices at t-2 and t-1; body_prev, body_next: [V, 3]
        (only the body rows are used) its body at t-1 and t. ``velocity`` scales and ``smooth``
        (a [V, 3] -> [V, 3] low-pass, as :func:`mixed_prediction`) filters the velocity.
        """
        from ..garment.garment import attachment_positions

        g, b = self.garment_ids, self.body_ids
        prev = np.asarray(prev, np.float64)
        dv = prev - np.asarray(prev2, np.float64)
        if smooth is not None:
            dv = smooth(dv)
        x = prev[g]
        bt, bt1 = np.asarray(body_prev, np.float64)[b], np.asarray(body_next, np.float64)[b]
        self.pushed = False
        if self._scene.has_intersections(np.vstack([x, bt])):
            # a tracked garment that has passed into the body: push the offending vertices out
            # along the body normal (as garment design does) to get an intersection-free start
            from ..garment.garment import push_out

            x = push_out(x, self._faces, [(bt, self.body_faces)], self.push_clearance, iters=10)[0]
            self.pushed = True
            if self._scene.has_intersections(np.vstack([x, bt])):
                self.last_stats = None
                return None
        targets = attachment_positions(self.attachment, bt1)
        x1, _, self.last_stats = self.sim.step(x, velocity * dv[g] / self.h, bt, bt1, self.body_faces, targets)
        out = prev.copy()
        out[b] = bt1
        out[g] = x1
        return out


def physics_predictor(cap: Capture, cfg: TrackConfig) -> PhysicsPrediction:
    """The :class:`PhysicsPrediction` of ``cfg`` for the capture's template."""
    from ..sim import SimSettings, preset

    t = cap.template
    return PhysicsPrediction(t.vertices, t.faces, t.labels, t.boundary, preset(cfg.prediction_material), cap.fps,
                             SimSettings(max_newton_iterations=cfg.prediction_newton_iterations))


# -- one frame -----------------------------------------------------------------------------------

@dataclass
class FrameResult:
    vertices: np.ndarray
    colors: np.ndarray
    iterations: int
    terms: dict = field(default_factory=dict)


def _loss_terms(model: MeshGaussians, vertices, colors, log_scales, opacity_logits, views: list[View],
                cfg: TrackConfig, iso: IsometryLoss | None, normal: NormalLoss | None,
                collision: CollisionLoss | None = None, anchor: AnchorLoss | None = None) -> dict:
    preds, alphas = [], []
    splats = model.splats(vertices, colors, log_scales, opacity_logits)
    for v in views:
        out = model.rasterize(splats, v.camera)
        preds.append(linear_to_srgb(out["rgb"]))
        alphas.append(out["alpha"])
    pred = torch.stack(preds)
    target = torch.stack([v.image for v in views])
    l1 = (pred - target).abs().mean()
    s = ssim(pred, target)
    terms = {"l1": l1, "ssim": s}
    render = cfg.l1_weight * l1 + (1 - cfg.l1_weight) * (1 - s)
    if cfg.mask_weight > 0:
        m = (torch.stack(alphas) - torch.stack([v.mask for v in views])).abs().mean()
        terms["mask"] = m
        render = render + cfg.mask_weight * m
    terms["render"] = render
    loss = render
    if iso is not None:
        terms["iso"] = iso(vertices)
        loss = loss + cfg.iso_weight * terms["iso"]
    if normal is not None:
        terms["normal"] = normal(vertices)
        loss = loss + cfg.normal_weight * terms["normal"]
    if collision is not None:
        terms["collision"] = collision(vertices)
        loss = loss + cfg.collision_weight * terms["collision"]
    if anchor is not None:
        terms["anchor"] = anchor(vertices)
        loss = loss + cfg.anchor_weight * terms["anchor"]
    terms["loss"] = loss
    return terms


def fit_frame(model: MeshGaussians, vertices: np.ndarray, pyramid: list[list[View]], cfg: TrackConfig,
              first: bool, iso: IsometryLoss | None = None, normal: NormalLoss | None = None,
              solve=None, collision: CollisionLoss | None = None, anchor: AnchorLoss | None = None) -> FrameResult:
    """Fit one frame over the pyramid (coarse to fine).

    ``first``: optimize colours, log-scales and opacity logits of ``model`` in place (vertices
    fixed); otherwise optimize ``vertices`` and colours, leaving scales and opacities alone.
    Returns the fitted vertices and colours (also left in ``model.colors``).
    """
    V0 = torch.from_numpy(np.asarray(vertices, np.float32)).clone()
    U = torch.zeros_like(V0)  # the smoothed offset's parameter (x = V0 + M^-1 U)

    def current():
        if first:
            return V0
        return V0 + (SmoothedSolve.apply(U, solve) if solve is not None else U)

    colors = model.colors.clone().requires_grad_(True)
    if first:
        log_scales = model.log_scales.clone().requires_grad_(True)
        opac = model.opacity_logits.clone().requires_grad_(True)
        groups = [(colors, cfg.lr_colors), (log_scales, cfg.lr_scales), (opac, cfg.lr_opacity)]
        iso = normal = collision = anchor = None  # vertices are fixed: these terms are constants
    else:
        log_scales, opac = model.log_scales, model.opacity_logits
        U.requires_grad_(True)
        groups = [(colors, cfg.lr_colors_track), (U, cfg.lr_vertices)]
    if not first:
        cfg = replace(cfg, mask_weight=cfg.mask_weight_track)
    n_levels = [cfg.iters_first] * len(pyramid) if first else (
        list(cfg.level_iters) if cfg.level_iters is not None else [cfg.iters] * len(pyramid))
    finest_px = pyramid[-1][0].camera.width
    total_iters = 0
    terms = {}
    for views, n_max in zip(pyramid, n_levels):
        # larger pixels, larger vertex steps: keep the step a fixed fraction of a pixel
        px_ratio = finest_px / views[0].camera.width
        lrs = [lr * (px_ratio if p is U else 1.0) for p, lr in groups]
        decay = cfg.lr_decay ** (1.0 / max(n_max - 1, 1))
        opts = []
        for (p, _), lr in zip(groups, lrs):
            kind = AdamUniform if (p is U and cfg.vertex_optimizer == "uniform") else torch.optim.Adam
            opts.append(kind([p], lr=lr, quantile=cfg.uniform_quantile) if kind is AdamUniform else kind([p], lr=lr))
        scheds = [torch.optim.lr_scheduler.ExponentialLR(o, decay) for o in opts]
        history: list[float] = []
        for it in range(n_max):
            for o in opts:
                o.zero_grad(set_to_none=True)
            terms = _loss_terms(model, current(), colors, log_scales, opac, views, cfg, iso, normal, collision, anchor)
            terms["loss"].backward()
            for o, sc in zip(opts, scheds):
                o.step()
                sc.step()
            with torch.no_grad():
                colors.clamp_(0.0, 1.0)
            history.append(float(terms["loss"].detach()))
            total_iters += 1
            k = cfg.check_every
            if it + 1 >= max(cfg.min_iters, 2 * k) and (it + 1) % k == 0:
                prev, last = np.mean(history[-2 * k:-k]), np.mean(history[-k:])
                if prev - last < cfg.plateau_tol * abs(prev):
                    break
    with torch.no_grad():
        V = current().detach()
        final = _loss_terms(model, V, colors.detach(), log_scales.detach(), opac.detach(),
                            pyramid[-1], cfg, iso, normal, collision, anchor)
    model.colors = colors.detach().clone()
    if first:
        model.log_scales = log_scales.detach().clone()
        model.opacity_logits = opac.detach().clone()
    return FrameResult(V.numpy().astype(np.float32), model.colors.numpy().astype(np.float32),
                       total_iters, {k: float(v) for k, v in final.items()})


def flow_start(cfg: TrackConfig, t, train: list[Camera], first_vertices: np.ndarray, first_grey: list[np.ndarray],
               skinned: np.ndarray):
    """The :class:`~physavatar.stages.flow.FlowStart` of the free garment (``~skinned``) of
    template ``t``, its reference the tracked first frame (``first_grey``: its training views)."""
    from .flow import FlowPrediction, FlowStart

    garment_faces = t.faces[t.garment_mask[t.faces].all(1)]
    body_faces = t.faces[(~t.garment_mask[t.faces]).all(1)]
    lift = FlowPrediction(t.faces, ~skinned, garment_faces, smoothness=cfg.flow_smoothness, rest=t.vertices,
                          iso_weight=cfg.flow_iso, collider_faces=body_faces, collision_weight=cfg.flow_collision,
                          bend_weight=cfg.flow_bend)
    return FlowStart(lift, train, first_vertices, first_grey, cfg.flow_corrections, cfg.flow_final_corrections,
                     dict(smoothness=cfg.flow_correction_smoothness, prior_weight=cfg.flow_correction_prior,
                          iso_weight=cfg.flow_correction_iso, bend_weight=cfg.flow_correction_bend))


def _grey_views(cap: Capture, frame: int, cameras: list[Camera]) -> list[np.ndarray]:
    return [to_gray8(cap.image(c.name, frame)) for c in cameras]


# -- the stage -----------------------------------------------------------------------------------

def _check_config(cfg: TrackConfig, capture: Capture) -> tuple[list[Camera], list[int]]:
    names = [c.name for c in capture.cameras]
    hold = default_holdout(names) if cfg.holdout is None else cfg.holdout
    unknown = [h for h in hold if h not in names]
    if unknown:
        raise PhysavatarError(capture.root / "cameras.json",
                              f"held-out camera(s) {', '.join(unknown)} not in the capture (cameras: {', '.join(names)})")
    train = [c for c in capture.cameras if c.name not in hold]
    if not train:
        raise PhysavatarError(None, f"option --holdout: holding out {', '.join(hold)} leaves no camera to fit")
    n = len(capture.frames) if cfg.n_frames is None else cfg.n_frames
    if n < 1 or n > len(capture.frames):
        raise PhysavatarError(None, f"option --frames: must be between 1 and {len(capture.frames)} (the capture's frames), got {n}")
    if not 0 < cfg.scale <= 1:
        raise PhysavatarError(None, f"option --scale: must be in (0, 1], got {cfg.scale}")
    if cfg.iters < 1 or cfg.iters_first < 1:
        raise PhysavatarError(None, "options --iters/--iters-first: need at least one iteration")
    if cfg.init not in ("mixed", "lbs", "velocity"):
        raise PhysavatarError(None, f"init must be 'mixed', 'lbs' or 'velocity', got {cfg.init!r}")
    if cfg.vertex_optimizer not in ("uniform", "adam"):
        raise PhysavatarError(None, f"vertex_optimizer must be 'uniform' or 'adam', got {cfg.vertex_optimizer!r}")
    if cfg.normal_mode not in ("paper", "rest"):
        raise PhysavatarError(None, f"normal_mode must be 'paper' or 'rest', got {cfg.normal_mode!r}")
    if not cfg.levels or any(not 0 < lv <= 1 for lv in cfg.levels):
        raise PhysavatarError(None, f"levels must be fractions in (0, 1], got {cfg.levels}")
    if cfg.level_iters is not None and (len(cfg.level_iters) != len(cfg.levels) or min(cfg.level_iters) < 1):
        raise PhysavatarError(None, f"level_iters needs one count >= 1 per level {cfg.levels}, got {cfg.level_iters}")
    if cfg.garment_prediction not in ("velocity", "physics", "flow"):
        raise PhysavatarError(None, f"garment_prediction must be 'velocity', 'physics' or 'flow', got {cfg.garment_prediction!r}")
    if min(cfg.flow_corrections, cfg.flow_final_corrections, cfg.flow_smoothness, cfg.flow_iso, cfg.flow_bend,
           cfg.flow_collision,
           cfg.flow_correction_smoothness, cfg.flow_correction_prior, cfg.flow_correction_iso,
           cfg.flow_correction_bend) < 0:
        raise PhysavatarError(None, "the flow_* settings must be >= 0, got "
                                    + ", ".join(f"{f.name}={getattr(cfg, f.name)}" for f in fields(cfg)
                                                if f.name.startswith("flow_")))
    if cfg.garment_prediction == "physics":
        from ..sim import PRESETS

        if cfg.prediction_material not in PRESETS:
            raise PhysavatarError(None, f"prediction_material must be one of {sorted(PRESETS)}, got {cfg.prediction_material!r}")
    for c in train:
        if min(round(c.width * cfg.scale * min(cfg.levels)), round(c.height * cfg.scale * min(cfg.levels))) < 11:
            raise PhysavatarError(None, f"option --scale: camera {c.name} would be smaller than 11 px "
                                        "at the coarsest level (SSIM's window); use a larger --scale")
    return train, capture.frames[:n]


def _read_log(path: Path) -> dict[int, dict]:
    if not path.is_file():
        return {}
    rows = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            rows[int(r["frame"])] = r
    return rows


def _write_log(path: Path, rows: dict[int, dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=LOG_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for f in sorted(rows):
        w.writerow(rows[f])
    write_text_atomic(path, buf.getvalue())


def _resume_key(d: dict) -> dict:
    return {k: v for k, v in d.items() if k != "n_frames"}


@dataclass
class TrackResult:
    """vertices [T, V, 3] float32, face_colors [T, F, 3], frames [T], computed: frames fitted by
    this call (the others were read back from a previous run), seconds per fitted frame."""

    out: Path
    frames: list[int]
    vertices: np.ndarray
    face_colors: np.ndarray
    computed: list[int]
    seconds: dict[int, float]


def track(capture: Capture | str | Path, out: str | Path, config: TrackConfig = TrackConfig(),
          progress: bool = True) -> TrackResult:
    """Track the capture's template through its frames (see the module docstring for outputs)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    cap = capture if isinstance(capture, Capture) else load_capture(capture)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise PhysavatarError(out, "output exists and is not a folder")
    train, frames = _check_config(config, cap)
    train_names = {c.name for c in train}
    cfg = replace(config, holdout=tuple(c.name for c in cap.cameras if c.name not in train_names))
    cfg_json = cfg.to_json()
    cfg_json["capture"] = str(Path(cap.root).resolve())
    old_path = out / "config.json"
    if old_path.is_file():
        old = read_json(old_path)
        # a run written before an option existed ran with that option's default
        old = {**{k: v for k, v in TrackConfig().to_json().items() if k not in old}, **old}
        if _resume_key(old) != _resume_key(cfg_json):
            diff = sorted(k for k in set(old) | set(cfg_json) if k != "n_frames" and old.get(k) != cfg_json.get(k))
            raise PhysavatarError(out, f"holds a tracking run with another config (differs in: {', '.join(diff)}); "
                                       "choose another --out or delete it")
    write_json_atomic(old_path, cfg_json)
    torch.manual_seed(cfg.seed)
    import numba

    old_threads = (torch.get_num_threads(), numba.get_num_threads())
    torch.set_num_threads(cfg.threads)
    numba.set_num_threads(min(cfg.threads, numba.config.NUMBA_NUM_THREADS))
    try:
        return _track(cap, out, cfg, train, frames, progress)
    finally:
        torch.set_num_threads(old_threads[0])
        numba.set_num_threads(old_threads[1])


def _track(cap: Capture, out: Path, cfg: TrackConfig, train: list[Camera], frames: list[int],
           progress: bool) -> TrackResult:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn


    t = cap.template
    model = MeshGaussians.init(t.vertices, t.faces, cfg.subdivide, cfg.opacity, cfg.antialiased)
    iso = IsometryLoss(t.vertices, t.faces) if cfg.iso_weight > 0 else None
    normal = (NormalLoss(t.faces, t.vertices if cfg.normal_mode == "rest" else None)
              if cfg.normal_weight > 0 else None)
    factors = [cfg.scale * lv for lv in cfg.levels]
    solve = smoothing_solver(len(t.vertices), t.faces, cfg.smoothing) if cfg.smoothing > 0 else None
    log_path = out / "track_log.csv"
    log = _read_log(log_path)
    skin = (TemplateSkinning.from_capture(cap, cfg.body_residual, cfg.garment_residual)
            if cfg.init in ("lbs", "mixed") and len(frames) > 1 else None)
    # body and garment-boundary vertices: placed by skinning under "mixed"
    skinned = ~t.garment_mask | t.boundary
    collision = anchor = None
    vsmooth = smoothing_solver(len(t.vertices), t.faces, cfg.velocity_smoothing) if cfg.velocity_smoothing > 0 else None
    physics = flow = None
    use_flow = cfg.init == "mixed" and skin is not None and cfg.garment_prediction == "flow" and (~skinned).any()
    grey: dict[int, list[np.ndarray]] = {}  # frame -> training views' luma, for the flow start
    if cfg.init == "mixed" and skin is not None:
        if cfg.garment_prediction == "physics" and (~skinned).any():
            physics = physics_predictor(cap, cfg)
        if cfg.anchor_weight > 0:
            anchor = AnchorLoss(np.flatnonzero(skinned))
        body_faces = t.faces[(~t.garment_mask[t.faces]).all(1)]
        if cfg.collision_weight > 0 and len(body_faces) and (~skinned).any():
            collision = CollisionLoss(np.flatnonzero(~skinned), np.flatnonzero(~t.garment_mask), body_faces,
                                      cfg.collision_margin)

    verts: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    computed: list[int] = []
    seconds: dict[int, float] = {}
    cols_ = (TextColumn("[bold]track[/] {task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*cols_, disable=not progress) as bar:
        task = bar.add_task("frames", total=len(frames))
        for i, f in enumerate(frames):
            fpath = out / "frames" / f"{frame_name(f)}.npz"
            if fpath.is_file():
                z = load_npz(fpath)
                verts.append(z["vertices"])
                cols.append(z["face_colors"])
                model.colors = torch.from_numpy(z["gaussian_colors"]).float()
                if i == 0:
                    model.log_scales = torch.from_numpy(z["log_scales"]).float()
                    model.opacity_logits = torch.from_numpy(z["opacity_logits"]).float()
                    model.edge_index = torch.from_numpy(z["edge_index"]).long()
                bar.advance(task)
                continue
            t0 = time.perf_counter()
            images = [cap.image(c.name, f) for c in train]
            pyramid = [load_views(cap, f, train, s, cfg.target_blur, images) for s in factors]
            if use_flow:
                grey[f] = [to_gray8(im) for im in images]
            if i == 0:
                gv = model.gaussian_vertices(torch.from_numpy(np.asarray(t.vertices, np.float32))).numpy()
                model.colors = torch.from_numpy(initial_colors(gv, model.faces.numpy(), pyramid[-1]))
                init = np.asarray(t.vertices, np.float32)
            elif cfg.init == "mixed":
                init = mixed_prediction(skin, i, verts, cfg.velocity, skinned, vsmooth)
                if use_flow:
                    if frames[i - 1] not in grey:  # resumed: frame t-1 came from disk
                        grey[frames[i - 1]] = _grey_views(cap, frames[i - 1], train)
                    if flow is None:  # built here, not before the loop: frame 1 may come from a resumed run
                        first = grey.get(frames[0]) or _grey_views(cap, frames[0], train)
                        flow = flow_start(cfg, t, train, verts[0], first, skinned)
                    init = flow(verts[-1], grey.pop(frames[i - 1]), grey[f], init).astype(np.float32)
                if physics is not None and i >= 2:
                    p = physics(verts[-2], verts[-1], skin.skin(i - 1), skin.skin(i), cfg.velocity, vsmooth)
                    if p is not None:  # None: the tracked garment intersects the body, keep velocity
                        init[~skinned] = p[~skinned]
            elif skin is not None:
                init = skin.predict(i, verts, cfg.velocity)
            else:
                prev = verts[-1]
                vel = verts[-1] - verts[-2] if i >= 2 else np.zeros_like(prev)
                init = prev + np.float32(cfg.velocity) * vel
            for term in (collision, anchor):
                if term is not None and i > 0:
                    term.update(init)
            res = fit_frame(model, init, pyramid, cfg, first=(i == 0), iso=iso, normal=normal, solve=solve,
                            collision=collision, anchor=anchor)
            if flow is not None and i > 0 and cfg.flow_final_corrections > 0:
                res.vertices = flow.refine(res.vertices, grey[f]).astype(np.float32)
            dt = time.perf_counter() - t0
            extra = {}
            if i == 0:
                extra = dict(log_scales=model.log_scales.numpy(), opacity_logits=model.opacity_logits.numpy(),
                             edge_index=model.edge_index.numpy())
            face_colors = model.face_colors(len(t.faces))
            save_npz_atomic(fpath, vertices=res.vertices, face_colors=face_colors, gaussian_colors=res.colors,
                            frame=np.int64(f), **extra)
            write_ply(out / "meshes" / f"{frame_name(f)}.ply",
                      PlyMesh(res.vertices, t.faces, {"label": t.labels.astype(np.uint8),
                                                      "boundary": t.boundary.astype(np.uint8)}))
            row = {"frame": f, "iterations": res.iterations, "seconds": f"{dt:.3f}"}
            row.update({k: f"{res.terms.get(k, 0.0):.6g}" for k in LOG_COLUMNS[2:-1]})
            log[f] = row
            _write_log(log_path, log)
            verts.append(res.vertices)
            cols.append(face_colors)
            computed.append(f)
            seconds[f] = dt
            bar.update(task, advance=1, description=f"frame {frame_name(f)}: {res.iterations} it, "
                                                    f"loss {res.terms['loss']:.4f}, {dt:.1f} s")
    V = np.stack(verts).astype(np.float32)
    C = np.stack(cols).astype(np.float32)
    TrackedSequence(V, t.faces, t.labels, t.boundary, C, np.asarray(frames, np.int64),
                    log_scales=model.log_scales.numpy(), opacity_logits=model.opacity_logits.numpy(),
                    edge_index=model.edge_index.numpy(), fps=float(cap.fps)).save(out / TRACKED)
    return TrackResult(out, list(frames), V, C, computed, seconds)
