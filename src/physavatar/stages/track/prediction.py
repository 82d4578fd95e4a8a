"""Where each frame t > 1 starts before its fit (``TrackConfig.prediction``).

- :class:`TemplateSkinning`: the template skinned by the capture's body poses (body.npz).
- :func:`mixed_prediction` (``init="mixed"``): body and garment boundary skinned, the free
  garment continuing its own motion; its start refined by the optical flow
  (:func:`flow_start`, ``garment="flow"``) or one cloth-simulator step
  (:class:`PhysicsPrediction`, ``garment="physics"``).
- :class:`FrameStarts`: the stage's per-frame driver of all of these.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...camera import Camera
from ...capture import Capture
from .config import FlowConfig, PredictionConfig, TrackConfig
from .fit import smoothing_solver
from .flow import FlowPrediction, FlowStart, to_gray8, to_rgb8
from .views import flow_views


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
    def from_capture(cap: Capture, body_residual: float = 1.0, garment_residual: float = 1.0) -> TemplateSkinning:
        from types import SimpleNamespace

        from ...body import BodyModel
        from ...garment import garment_skinning_weights

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
        frame t, which drives it; carrying its residual only accumulates each frame's photometric
        error).
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
    x_{t-1} + velocity (x_{t-1} - x_{t-2}). A simulated garment does not follow skinning (the
    legs drag a skirt): skinned, it starts centimetres further off than on its own motion.
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
        material: :class:`physavatar.sim.Material` (a prior: the real one is not known yet); with
            ``rest_shape`` "equilibrium" the garment's rest shape is the one whose static
            equilibrium on the template's body is the template (garment_sim.equilibrium_part).
        fps: the capture's frame rate. settings: :class:`physavatar.sim.SimSettings` (dt is
            replaced by 1/fps).
        push_clearance: a tracked garment that intersects the body at t-1 is first pushed out
            to this distance [m] (:func:`physavatar.garment.garment.push_out`); if it still
            intersects, there is no prediction (None).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, boundary: np.ndarray,
                 material, fps: float, settings=None, push_clearance: float = 1e-3):
        from ...garment.garment import make_attachment
        from ...garment_sim import equilibrium_part, split_template
        from ...sim import ClothSim, SimSettings
        from ...sim.contact import ContactScene

        V = np.asarray(vertices, np.float64)
        self.body_ids, self.body_faces, part = split_template(V, np.asarray(faces), np.asarray(labels),
                                                              np.asarray(boundary, bool))
        self.garment_ids = part.vertex_ids
        self.boundary = part.boundary
        self.h = 1.0 / fps
        settings = replace(settings or SimSettings(), dt=self.h)
        # with the material's rest shape "equilibrium": the template is the static equilibrium (sim.rest)
        part, self.rest_report = equilibrium_part(part, V[self.body_ids], self.body_faces, material, settings)
        self.sim = ClothSim(part.rest_shape, part.faces, material, settings, part.boundary)
        self.attachment = make_attachment(part.vertices[part.boundary], part.boundary, V[self.body_ids],
                                          self.body_faces, "sequence")
        # the intersection test of the start state (ipctk's CCD assumes an intersection-free start)
        self._scene = ContactScene(part.vertices, part.faces, V[self.body_ids], self.body_faces, settings.dhat)
        self._faces = part.faces
        # Each call one step from the same sim state: the contact scene built on the template's body
        # (ipctk takes its mollifier thresholds from the rest positions) and the initial barrier
        # stiffness (which IPC adapts from step to step). A call's result then depends on its
        # arguments alone, so a resumed tracking run predicts what an uninterrupted one does.
        self.sim.prepare(V[self.body_ids], self.body_faces)
        self._state0 = self.sim.get_state()
        self._settings0, self._scene_dmin0 = self.sim.settings, self.sim.scene.dmin
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
        from ...garment.garment import attachment_positions

        g, b = self.garment_ids, self.body_ids
        prev = np.asarray(prev, np.float64)
        dv = prev - np.asarray(prev2, np.float64)
        if smooth is not None:
            dv = smooth(dv)
        x = prev[g]
        bt, bt1 = np.asarray(body_prev, np.float64)[b], np.asarray(body_next, np.float64)[b]
        self.pushed = False
        if self._scene.has_intersections(np.vstack([x, bt])):
            x = self.feasible(x, bt)
            self.pushed = True
            if x is None:
                self.last_stats = None
                return None
        targets = attachment_positions(self.attachment, bt1)
        self.sim.set_state(self._state0)
        x = self._thickness(x, bt)
        x1, _, self.last_stats = self.sim.step(x, velocity * dv[g] / self.h, bt, bt1, self.body_faces, targets)
        out = prev.copy()
        out[b] = bt1
        out[g] = x1
        return out

    def _thickness(self, x: np.ndarray, body: np.ndarray) -> np.ndarray:
        """``x`` lifted off ``body`` to the material's contact thickness (``contact_offset``,
        ipctk's d_min, which fit-physics' material.json records: its barrier is undefined closer
        than that, and a tracked frame is not held off the body by it), the sim's thickness
        lowered for this step where the lift cannot reach it (sim.simulate.feasible_thickness)."""
        from ...sim.simulate import feasible_thickness

        self.sim.settings, self.sim.scene.dmin = self._settings0, self._scene_dmin0
        if self.sim.dmin <= 0:
            return x
        x, settings = feasible_thickness(self.sim, x, body, self.body_faces)
        if settings.dmin != self._settings0.dmin:
            self.sim.settings, self.sim.scene.dmin = settings, settings.dmin
        return x

    def feasible(self, x: np.ndarray, body: np.ndarray) -> np.ndarray | None:
        """[Ng, 3] the garment ``x`` that intersects ``body`` made intersection-free, or None:
        first :func:`physavatar.sim.untangle.untangle` (cloth inside the body, by winding number,
        to 2 d̂ outside its closest outer point; edges through it lifted; session 26), then, if it
        still crosses, the offending vertices pushed out along the body normal
        (:func:`physavatar.garment.garment.push_out`, as garment design does)."""
        from ...garment.garment import push_out
        from ...sim.untangle import untangle

        free = np.ones(len(x), bool)
        free[self.boundary] = False
        y, moved = untangle(self._scene, x, self._faces, body, self.body_faces, free, self.sim.settings.dhat)
        if len(moved):
            return y
        x = push_out(x, self._faces, [(body, self.body_faces)], self.push_clearance, iters=10)[0]
        return None if self._scene.has_intersections(np.vstack([x, body])) else x


def physics_predictor(cap: Capture, cfg: PredictionConfig) -> PhysicsPrediction:
    """The :class:`PhysicsPrediction` of ``cfg`` for the capture's template."""
    from ...sim import Material, SimSettings, preset

    t = cap.template
    material = Material.load(cfg.material) if cfg.material.endswith(".json") else preset(cfg.material)
    if cfg.rest_shape != "material":
        material = replace(material, rest_shape=cfg.rest_shape)
    return PhysicsPrediction(t.vertices, t.faces, t.labels, t.boundary, material, cap.fps,
                             SimSettings(max_newton_iterations=cfg.newton_iterations))

def flow_start(cfg: FlowConfig, t, train: list[Camera], first_vertices: np.ndarray, first_grey: list[np.ndarray],
               skinned: np.ndarray):
    """The :class:`~physavatar.stages.track.flow.FlowStart` of the free garment (``~skinned``) of
    template ``t``, its reference the tracked first frame (``first_grey``: its training views)."""

    garment_faces = t.faces[t.garment_mask[t.faces].all(1)]
    body_faces = t.faces[(~t.garment_mask[t.faces]).all(1)]
    lift = FlowPrediction(t.faces, ~skinned, garment_faces, smoothness=cfg.smoothness, rest=t.vertices,
                          iso_weight=cfg.iso, collider_faces=body_faces, collision_weight=cfg.collision,
                          bend_weight=cfg.bend, bend_huber=cfg.bend_huber, prior_weight=cfg.prior,
                          bend_reference=cfg.bend_reference, bend_moved=cfg.bend_moved,
                          bend_views=cfg.bend_views, min_texture=cfg.min_texture,
                          highpass=cfg.highpass, texture_blur=cfg.texture_blur)
    return FlowStart(lift, train, first_vertices, first_grey, cfg.corrections, cfg.final_corrections,
                     dict(smoothness=cfg.correction_smoothness, prior_weight=cfg.correction_prior,
                          iso_weight=cfg.correction_iso, bend_weight=cfg.correction_bend,
                          silhouette_weight=cfg.silhouette, channels=cfg.channels,
                          bend_reference=cfg.correction_bend_reference or cfg.bend_reference), cfg.coarse,
                     predict_colour=cfg.predict_colour)



PLAIN_BLUR = 1.0  # [px] the blur under which a plain garment's texture is measured (FlowConfig.plain)


class FrameStarts:
    """The start of every frame t > 1 of a run (``cfg.prediction``), and the flow corrections after
    its fit. Frames are fed in order: :meth:`observe` each fitted frame's images, then
    :meth:`start` it, then :meth:`refine` its fit.

    Attributes:
        skin: the :class:`TemplateSkinning` (None under ``init="velocity"`` or for one frame).
        skinned: [V] bool, the vertices placed by skinning under ``init="mixed"`` (the body and
            the garment's boundary).
        mixed: whether ``init="mixed"`` applies (the body and the boundary are skinned).
    """

    def __init__(self, cap: Capture, cfg: TrackConfig, train: list[Camera], frames: list[int]):
        p = cfg.prediction
        t = cap.template
        self.cap, self.cfg, self.train, self.frames, self.template = cap, cfg, train, list(frames), t
        self.skin = (TemplateSkinning.from_capture(cap, p.body_residual, p.garment_residual)
                     if p.init in ("lbs", "mixed") and len(frames) > 1 else None)
        self.skinned = ~t.garment_mask | t.boundary
        self.smooth = (smoothing_solver(len(t.vertices), t.faces, p.velocity_smoothing)
                       if p.velocity_smoothing > 0 else None)
        self.mixed = p.init == "mixed" and self.skin is not None
        free = bool((~self.skinned).any())
        self.use_flow = self.mixed and p.garment == "flow" and free
        # the physics step: the start itself ("physics"), or the flow lift's reference (flow.carry "physics")
        physics = p.garment == "physics" or (self.use_flow and cfg.flow.carry == "physics")
        self.physics = physics_predictor(cap, p) if self.mixed and physics and free else None
        self.physics_frames: dict[int, str] = {}  # frame -> "stepped" / "untangled" / "none" (no valid start)
        self.flow: FlowStart | None = None  # built at frame 2: frame 1 may come from a resumed run
        self._grey: dict[int, list[np.ndarray]] = {}  # frame -> training views' luma (sRGB: colour flow)
        self._masks: dict[int, list[np.ndarray]] = {}  # frame -> training views' masks (silhouette term)
        self._carry_w: np.ndarray | None = None
        self.flow_cfg: FlowConfig = cfg.flow  # cfg.flow with the plain-garment rule (set at frame 2)
        self.plain: bool | None = None
        self.garment_texture: float | None = None

    def observe(self, frame: int, images: list[np.ndarray]) -> None:
        """The training views of ``frame`` (full-resolution sRGB), kept as grey for the flow, and
        their masks for the corrections' silhouette term."""
        if self.use_flow:
            convert = to_rgb8 if self.cfg.flow.channels == "colour" else to_gray8
            self._grey[frame] = [convert(im) for im in images]
            if self.cfg.flow.silhouette > 0 and self.cap.has_masks and frame != self.frames[0]:
                self._masks[frame] = [self.cap.mask(c.name, frame) for c in self.train]

    def start(self, i: int, tracked: list[np.ndarray]) -> np.ndarray:
        """[V, 3] float32 start of ``frames[i]`` (i >= 1) from ``tracked``, the fitted frames before it."""
        p = self.cfg.prediction
        if self.mixed:
            init = mixed_prediction(self.skin, i, tracked, p.velocity, self.skinned, self.smooth)
            if self.use_flow:
                prev, f = self.frames[i - 1], self.frames[i]
                if prev not in self._grey:  # resumed: frame t-1 came from disk
                    self._grey[prev] = flow_views(self.cap, prev, self.train, self.cfg.flow.channels)
                if self.flow is None:
                    first = (self._grey.get(self.frames[0])
                             or flow_views(self.cap, self.frames[0], self.train, self.cfg.flow.channels))
                    self.flow_cfg = self._flow_settings(tracked[0], first)
                    self.flow = flow_start(self.flow_cfg, self.template, self.train, tracked[0], first, self.skinned)
                carried = None
                if self.flow_cfg.carry == "velocity":  # no motion: the garment's own constant velocity
                    carried = np.asarray(init, np.float64).copy()
                elif self.flow_cfg.carry == "physics":  # no motion: one simulator step (session 26)
                    x = self._physics_step(i, tracked, p)
                    if x is not None:  # the start and the prior of the lift too
                        carried = x
                        carried[self.skinned] = init[self.skinned]
                        init = carried.astype(np.float32)
                if self.flow_cfg.carry in ("body", "near"):  # frame t-1 moved with the body to t
                    prev_x = np.asarray(tracked[-1], np.float64)
                    carried = self.skin.skin(i, self.skin.unskin(i - 1, prev_x))
                    if self.flow_cfg.carry == "near":  # by how close the cloth lies on the body
                        w = self.carry_weights()[:, None]
                        carried = prev_x + w * (carried - prev_x)
                    carried[self.skinned] = init[self.skinned]
                init = self.flow(tracked[-1], self._grey.pop(prev), self._grey[f], init,
                                 self._masks.get(f), carried).astype(np.float32)
            if self.physics is not None and not self.use_flow:
                x = self._physics_step(i, tracked, p)
                if x is not None:  # None: the tracked garment intersects the body, keep velocity
                    init[~self.skinned] = x[~self.skinned]
            return init
        if self.skin is not None:
            return self.skin.predict(i, tracked, p.velocity)
        prev = tracked[-1]
        vel = tracked[-1] - tracked[-2] if i >= 2 else np.zeros_like(prev)
        return prev + np.float32(p.velocity) * vel

    def _physics_step(self, i: int, tracked: list[np.ndarray], p: PredictionConfig) -> np.ndarray | None:
        """[V, 3] one simulator step of the tracked garment to ``frames[i]`` (:class:`PhysicsPrediction`),
        or None (frame 2, without a velocity yet, or no intersection-free start); noted in
        ``physics_frames``."""
        if i < 2:
            return None
        x = self.physics(tracked[-2], tracked[-1], self.skin.skin(i - 1), self.skin.skin(i), p.velocity, self.smooth)
        self.physics_frames[self.frames[i]] = "none" if x is None else "untangled" if self.physics.pushed else "stepped"
        return x

    def _flow_settings(self, first_vertices: np.ndarray, first_views: list[np.ndarray]) -> FlowConfig:
        """``cfg.flow`` with the plain-garment rule applied (:class:`FlowConfig` ``plain``): the
        texture of the first frame's views decides whether the flow is gated, the carry near and
        the fit's move of the free garment kept whole (``fit_blend`` 1).
        Sets ``self.garment_texture`` (None when not measured) and ``self.plain``."""
        fc = self.cfg.flow
        self.garment_texture = None
        if fc.plain == "auto":
            from .channels import garment_texture

            self.garment_texture = garment_texture(np.asarray(first_vertices, np.float64), self.template.faces,
                                                   ~self.skinned, self.train, first_views, PLAIN_BLUR)
        self.plain = fc.plain == "plain" or (fc.plain == "auto" and self.garment_texture < fc.plain_texture)
        if not self.plain:
            return fc
        # a plain garment's flow follows the shading: the fit (its masks) places the garment too
        return replace(fc, min_texture=max(fc.min_texture, fc.plain_texture), texture_blur=fc.texture_blur or PLAIN_BLUR,
                       carry="near" if fc.carry == "still" else fc.carry, fit_blend=1.0)

    def carry_weights(self) -> np.ndarray:
        """[V] how much of the body's motion each vertex takes as its "no motion" under
        ``flow.carry="near"``: exp(-(d / carry_range)^2), d its distance from the body surface in
        the template. Cloth that lies on the body (a fitted top) moves with it where no flow
        observes it; cloth that hangs away from it (a skirt's hem over the legs) keeps its own place."""
        if self._carry_w is None:
            from ...geometry import MeshQuery

            t = self.template
            V = np.asarray(t.vertices, np.float64)
            body_faces = t.faces[(~t.garment_mask[t.faces]).all(1)]
            r = self.cfg.flow.carry_range
            d = MeshQuery(V, body_faces).closest(V, max_dist=4 * r)[0] if len(body_faces) else np.full(len(V), np.inf)
            self._carry_w = np.exp(-np.square(np.minimum(d, 4 * r) / r))
        return self._carry_w

    def refine(self, i: int, vertices: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """``frames[i]``'s fitted ``vertices`` after ``flow.final_corrections`` flow corrections;
        with ``start`` (the frame's start) the free garment first keeps ``flow.fit_blend`` of the
        fit's move from it (1: all of it; a plain garment keeps all, :meth:`_flow_settings`)."""
        blend = self.flow_cfg.fit_blend if self.flow is not None else 1.0
        if i > 0 and start is not None and blend < 1:
            free = ~self.skinned
            vertices = np.array(vertices, np.float32, copy=True)
            vertices[free] = start[free] + blend * (vertices[free] - start[free])
        if self.flow is not None and i > 0 and self.cfg.flow.final_corrections > 0:
            f = self.frames[i]
            return self.flow.refine(vertices, self._grey[f], self._masks.pop(f, None)).astype(np.float32)
        return vertices
