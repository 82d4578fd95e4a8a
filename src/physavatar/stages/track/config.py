"""The tracking stage's settings: :class:`TrackConfig` and its groups (saved as config.json).

Fields with a command-line flag carry it (:func:`physavatar.stages.base.option`); the others are
settings (:func:`~physavatar.stages.base.setting`). docs/tracking.md explains the defaults and the
measurements behind them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from ..base import camera_list, option, setting


def _backend_problem(backend: str) -> str | None:
    """Why ``backend`` cannot render here (None when it can)."""
    from ...splat import _gsplat

    if backend == "gsplat" and not _gsplat.available():
        return "gsplat needs a CUDA device and the gsplat package (pip install -e .[gsplat]); use auto or numba"
    return None


@dataclass(frozen=True)
class FitConfig:
    """The photometric fit of each frame: image pyramid, optimizer and schedule.

    Attributes:
        scale: resolution factor of the finest pyramid level w.r.t. the capture's images.
        min_px: the finest level's longer side in pixels at least (``scale`` raised for a small
            capture, never above 1; 0: ``scale`` as given). See :func:`fit_scale`.
        levels: pyramid levels as fractions of ``scale``, coarse to fine.
        iters_first, iters: maximum iterations per level for frame 1 and for later frames.
        level_iters: maximum iterations of frames t > 1 per level (coarse to fine); None:
            ``iters`` on every level.
        min_iters, check_every, plateau_tol: a level stops early once the mean loss of the last
            ``check_every`` steps improved on the window before by less than ``plateau_tol``
            (relative), after at least ``min_iters`` steps.
        lr_vertices: Adam step size of the vertices at the finest level [m]; a level whose
            pixels are k times larger uses k times this.
        lr_decay: every level's step sizes decay exponentially to this fraction at its last step.
        lr_colors, lr_scales, lr_opacity: Adam step sizes on frame 1 (linear RGB, log-scale,
            logit). Scales and opacities stay fixed by default (0): per-face scales and
            opacities fitted to frame 1's silhouettes do not transfer to the faces that make the
            silhouette later.
        lr_colors_track: colour step size on frames t > 1 (0: fixed after frame 1). Colours that
            chase every frame's image absorb misalignment instead of exposing it to the vertices.
        vertex_optimizer: "uniform" (:class:`~physavatar.optim.uniform.AdamUniform`: one
            second-moment normaliser for all vertices) or "adam" (per-coordinate Adam).
        uniform_quantile: the uniform normaliser's quantile.
        smoothing: λ of the vertex update's smoothing (I + λ L)^-1
            (:class:`~physavatar.stages.track.fit.SmoothedSolve`); 0 optimizes the vertices directly.
        target_blur: Gaussian blur (px) of the target images and masks at each level, meant to
            match the splats' 0.3 px² low-pass (0: off).
        first_vertex_iters: frame 1's vertices fitted too, after its colours, with at most this
            many iterations per level (later frames' fit: their loss, regularisers and colour
            steps, on frame 1's images); 0 keeps frame 1 at the template (a template that is exact at frame 1).
    """

    scale: float = option(0.25, "resolution factor of the finest level, in (0, 1]")
    min_px: int = setting(0)
    levels: tuple[float, ...] = setting((0.5, 1.0))
    iters_first: int = option(150, "max iterations per pyramid level, frame 1")
    iters: int = option(15, "max iterations per pyramid level, later frames")
    level_iters: tuple[int, ...] | None = setting(None)
    min_iters: int = setting(20)
    check_every: int = setting(10)
    plateau_tol: float = setting(2e-3)
    lr_vertices: float = setting(4e-3)
    lr_decay: float = setting(0.1)
    lr_colors: float = setting(0.01)
    lr_scales: float = setting(0.0)
    lr_opacity: float = setting(0.0)
    lr_colors_track: float = setting(0.0)
    vertex_optimizer: str = setting("uniform")
    uniform_quantile: float = setting(0.5)
    smoothing: float = setting(10.0)
    target_blur: float = setting(0.0)
    first_vertex_iters: int = setting(0)


def fit_scale(fit: FitConfig, cameras) -> float:
    """The finest level's resolution factor for ``cameras``: ``fit.scale``, raised so the largest
    training image is at least ``fit.min_px`` pixels on its longer side there (at most 1)."""
    if fit.min_px <= 0:
        return fit.scale
    size = max(max(c.width, c.height) for c in cameras)
    return min(1.0, max(fit.scale, fit.min_px / size))


@dataclass(frozen=True)
class LossConfig:
    """The weights of the tracking loss (Eq. 4 plus an anchor and a collision term).

    Attributes:
        l1_weight: λ of Eq. 1 (0.8 as the official code: 0.8 L1 + 0.2 (1 - SSIM)).
        mask_weight: weight of |rendered alpha - mask| (0 ignores the masks) on frame 1;
            mask_weight_track on later frames (with colours fixed, the silhouette is the part of
            the image the frame-1 appearance model gets right).
        iso_weight, normal_weight: λ_iso, λ_n of Eq. 4 (0 for the ablation: ``--no-iso``,
            ``--no-normal``).
        normal_mode: "paper" (Eq. 3 as printed) or "rest" (change of each dihedral since frame
            1; see :class:`~physavatar.stages.track.losses.NormalLoss`).
        anchor_weight: weight of :class:`~physavatar.stages.track.losses.AnchorLoss` (1 cm units)
            holding the body and the garment boundary near their skinned pose under
            ``init="mixed"``: the capture's body poses place the body better than the images do.
        collision_weight, collision_margin: garment-body penalty
            (:class:`~physavatar.stages.track.losses.CollisionLoss`, the official code has one)
            and its margin [m]; 0 = off (with an unbiased silhouette it pushes penetrated cloth
            out on the wrong side as often as on the right one).
    """

    l1_weight: float = setting(0.8)
    mask_weight: float = setting(0.5)
    mask_weight_track: float = setting(1.0)
    iso_weight: float = setting(20.0)
    normal_weight: float = setting(0.1)
    normal_mode: str = setting("rest")
    anchor_weight: float = setting(1.0)
    collision_weight: float = setting(0.0)
    collision_margin: float = setting(0.001)


@dataclass(frozen=True)
class PredictionConfig:
    """Where each frame t > 1 starts before its fit (:mod:`physavatar.stages.track.prediction`).

    Attributes:
        init: "mixed" (default, :func:`~physavatar.stages.track.prediction.mixed_prediction`):
            body and garment boundary skinned to the body pose of frame t, the rest of the garment
            started by ``garment``. "lbs": the template skinned to the capture's body pose of
            frame t (body.npz, the body model's LBS; garment weights transferred from the closest
            body point), plus the previous frames' tracked residual from that skinning, carried in
            each vertex's local skinning frame and extrapolated with ``velocity``
            (:class:`~physavatar.stages.track.prediction.TemplateSkinning`). "velocity":
            v_{t-1} + velocity (v_{t-1} - v_{t-2}).
        garment: how the free garment starts under ``init="mixed"`` (``--garment-start``):
            "flow" (:mod:`physavatar.stages.track.flow`: the multi-view optical flow
            I_{t-1} -> I_t of the training cameras at full resolution lifted to the garment
            vertices, then model-based corrections against the first frame's projective texture;
            settings in :class:`FlowConfig`), "velocity" (x_{t-1} + velocity S(x_{t-1} - x_{t-2}))
            or "physics" (one implicit-Euler step of the cloth simulator from the last two tracked
            frames with that velocity, the body skinned to frames t-1 and t as collider:
            :class:`~physavatar.stages.track.prediction.PhysicsPrediction`; frames whose tracked
            garment intersects the body fall back to "velocity").
        velocity: factor of the constant-velocity term of each frame's prediction (0: none).
        velocity_smoothing: λ of a (I + λ L)^-1 low-pass of that velocity under ``init="mixed"``
            (0: the raw difference of the last two tracked frames).
        body_residual, garment_residual: the share of the body's / garment's tracked residual
            from skinning carried to the next frame with ``init="lbs"``. Below one, the start of
            each frame leans back toward the skinned pose, which bounds the drift: a per-frame
            fitting error b adds up to b / (1 - share) instead of growing without end.
        material: simulator material of the physics prediction and of ``flow.carry`` "physics": a
            preset name or a material .json (fit-physics' material.json: the paper's loop, a second
            tracking pass with the material fitted on the first). The garment's material is not
            known when tracking: a prior. A material with a contact thickness (``contact_offset``,
            which fit-physics records) first lifts each step's start off the body to it (session 29).
        newton_iterations: cap on the physics step's Newton iterations (capped too low, the step
            stays in the phase where the body sweeps into the cloth).
        rest_shape: the garment's rest shape in the physics step: "material" (what the material
            records: presets "template"; fit-physics --rest-shape equilibrium "equilibrium"),
            "template" (the template, loaded by gravity) or "equilibrium" (the shape whose static
            equilibrium on the template's body is the template; sim.rest, docs/physics.md). Session
            29: a better one-step prediction on the foreign skirt, the same tracking (docs/tracking.md).
    """

    init: str = option("mixed", "start of each frame: mixed (body and garment boundary skinned from body.npz, the rest "
                                "of the garment by --garment-start; default), lbs (all skinned + carried residual) or "
                                "velocity", choices=("mixed", "lbs", "velocity"))
    garment: str = option("flow", "start of the free garment under --init mixed: flow (multi-view optical flow + "
                                  "model-based corrections; default), velocity or physics",
                          flag="--garment-start", choices=("flow", "velocity", "physics"))
    velocity: float = setting(1.0)
    velocity_smoothing: float = setting(30.0)
    body_residual: float = setting(0.0)
    garment_residual: float = setting(0.5)
    material: str = setting("cotton")
    newton_iterations: int = setting(40)
    rest_shape: str = setting("material")


@dataclass(frozen=True)
class FlowConfig:
    """The optical-flow start of the free garment (``garment="flow"``;
    :class:`~physavatar.stages.track.flow.FlowPrediction`, :class:`~physavatar.stages.track.flow.FlowStart`).

    Attributes:
        smoothness: membrane smoothness of the flow lift (dimensionless).
        corrections: model-based flow corrections per frame before the fit (0: prediction only).
        iso: weight of the edge-length term of the flow lift, toward the template's lengths (the
            hem seen by one or two cameras is otherwise free to stretch along the rays).
        bend: weight of the bending term of the flow lift (distances across the garment's interior
            edges toward the template's: its folds' dihedral angles), so a fold cannot slide along
            itself where the edge lengths alone allow it.
        collision: penalty weight holding the free garment outside the body in every flow lift
            (0: off); a garment vertex inside the body is hidden from every camera, so no later
            flow would bring it back.
        final_corrections: model-based corrections after the photometric fit (the fit's own
            optimum at the fitting resolution lies a little off a corrected start).
        correction_smoothness, correction_prior, correction_iso, correction_bend: the
            corrections' lift: membrane smoothness, pull toward the estimate, edge-length and
            bending terms.
        bend_huber: [m] change of a hinge's distance up to which the bending terms (``bend``,
            ``correction_bend``) are quadratic; linear beyond (0: quadratic everywhere). A flared
            skirt forms and opens folds the template does not have; a quadratic pull toward the
            template's folds then moves the true shape by centimetres.
        silhouette: weight of the silhouette term in every correction
            (:mod:`~physavatar.stages.track.silhouette`: the estimate's outline pulled onto each
            training camera's mask outline at full resolution; 0: off). It sees what the flow
            cannot where the texture is aliased or plain. Default 4 since session 22 (it improved
            all three foreign captures and the demo's first frames; docs/tracking.md).
        prior: weight of the prediction's pull toward the constant-velocity start (the garment's
            momentum: x_{t-1} + S(x_{t-1} - x_{t-2})) in the flow lift of frame t-1 -> t (0: the
            observations and the regularisers alone decide; a vertex that no flow sees then
            moves only with its neighbours).
        channels: what the corrections' flow runs on: "luma" (grey) or "colour" (default since
            session 15: the luma and those colour-opponent channels in which the first frame's
            garment shows a pattern, each its own observations; none: the luma alone): a texture
            whose pattern is in its hues more than in its brightness keeps it.
        coarse: corrections per frame (before the fit) run first with the flow at half size,
            coarse to fine, for errors of several pixels an aliased texture hides.
        bend_reference: what the bending terms hold: "rest" (the template's hinge distances) or
            "start" (those of the mesh each lift starts from: the previous frame, the estimate) or
            "moved" (per hinge, the start's where its distance differs from the template's by
            more than ``bend_moved``, the template's elsewhere: a fold the garment has made is
            kept; session 28: tracking skirt 5.08 -> 4.78 mm, demo 48 frames 0.955 -> 0.917, tops
            0.629 -> 0.607 and 2.84 -> 2.78, but the whole demo's held-out garment CD 0.0432 ->
            0.0472 and motion PSNR 27.97 -> 27.52 dB, so not the default; docs/tracking.md);
            "physics" (session 37: the hinges of the frame's physics step, the lift's reference
            under ``carry`` "physics", in the prediction and the frame's corrections; the
            template's where there is no step).
        correction_bend_reference: the same for the corrections alone ("": as ``bend_reference``):
            "rest", "start", "moved", "physics" or "previous" (the hinges of the tracked frame
            t-1, fixed through the frame's corrections).
        bend_moved: [m] the threshold of ``bend_reference`` "moved" (sessions 22 and 28).
        bend_views: the cameras whose flow must see both vertices opposite a hinge for
            ``bend_reference`` "seen" to keep the start's distance there (session 24).
        fit_blend: the share of the photometric fit's move of the free garment (from the frame's
            flow start) that the frame keeps before its final corrections (1: all, as before
            session 24; 0, default since session 24: the fit places the body alone and the garment
            keeps its full-resolution flow start, which the quarter-resolution fit only pulled
            off; a plain garment, whose flow follows the shading, keeps the fit whole). Demo 48
            frames 1.835 -> 1.327 mm, skirt 5.38 -> 5.09, printed top 0.81 -> 0.71 (docs/tracking.md).
        min_texture: [levels per pixel] a flow observation counts only where the view it is
            measured from has at least this much texture in both directions
            (:func:`~physavatar.stages.track.channels.texture_strength`, per channel; 0: all). On a
            plain garment the flow follows the shading, which moves with the light, not the cloth.
        carry: what the prediction's lift takes as "no motion" for the free garment: "still"
            (frame t-1 where it was) or "body" (frame t-1 carried by the body's skinning from t-1
            to t), so what no flow observes follows the body instead of staying behind; "near":
            the body's motion weighted by exp(-(d / ``carry_range``)^2), d [m] the vertex's distance
            from the body in the template (a fitted top follows the torso, a skirt's hem does not
            follow the legs); "velocity" (session 26): the garment's constant-velocity start
            x_{t-1} + S(x_{t-1} - x_{t-2}); "physics" (session 26): one step of the cloth simulator
            from the last two tracked frames (:class:`~physavatar.stages.track.prediction.PhysicsPrediction`,
            material ``prediction.material``, the tracked garment first made intersection-free), also
            the lift's start and the target of ``prior``: where the flow sees the cloth it follows the
            images, where it does not the cloth keeps the simulator's motion (frames without a valid
            step keep "still").
        predict_colour: the prediction's frame-to-frame flow runs on the same channels as the
            corrections (``channels``: with "colour", the luma and the patterned opponent
            channels) instead of the luma alone.
        highpass: [px] every flow runs on its channels less their Gaussian blur of this width
            (:func:`~physavatar.stages.track.channels.shading_free`; 0: off): the flow of the
            texture that moves with the cloth, not of the shading that changes as it turns.
        texture_blur: [px] ``min_texture`` is measured on the view blurred by this Gaussian (0:
            as it is): texture finer than a pixel (a plain fabric's speckle) is aliased and does
            not move coherently with the cloth, a pattern of several pixels does.
        plain: whether the garment is plain, so its flow follows the shading more than the cloth:
            "auto" (default, session 18: plain when the median texture strength of the free
            garment's first-frame views blurred by 1 px,
            :func:`~physavatar.stages.track.channels.garment_texture`, is below
            ``plain_texture``), "plain" or "patterned". For a plain garment every flow observation
            counts only where the view blurred by 1 px has ``plain_texture`` of texture
            (``min_texture`` and ``texture_blur`` raised to that), and ``carry`` "still" becomes
            "near": what the flow does not see moves with the body it lies on.
        plain_texture: [levels per pixel] that threshold.
    """

    smoothness: float = setting(3.0)
    corrections: int = setting(3)
    iso: float = setting(3.0)
    bend: float = setting(10.0)
    collision: float = setting(1e3)
    final_corrections: int = setting(1)
    correction_smoothness: float = setting(0.1)
    correction_prior: float = setting(0.01)
    correction_iso: float = setting(10.0)
    correction_bend: float = setting(5.0)
    silhouette: float = setting(4.0)
    bend_huber: float = setting(0.0)
    prior: float = setting(0.0)
    channels: str = setting("colour")
    coarse: int = setting(0)
    bend_reference: str = setting("rest")
    correction_bend_reference: str = setting("")
    bend_moved: float = setting(0.002)
    bend_views: int = setting(2)
    fit_blend: float = setting(0.0)
    min_texture: float = setting(0.0)
    carry: str = setting("physics")
    predict_colour: bool = setting(False)
    highpass: float = setting(0.0)
    texture_blur: float = setting(0.0)
    carry_range: float = setting(0.02)
    plain: str = setting("auto")
    plain_texture: float = setting(1.2)


@dataclass(frozen=True)
class TrackConfig:
    """Everything that defines a tracking run (saved as config.json, nested by group).

    Attributes:
        n_frames: track only the first N frames (None: all). Not part of the resume check or the
            stage hash, so a run can be extended.
        holdout: camera names excluded from fitting; None = the default rule
            (:func:`~physavatar.stages.track.stage.default_holdout`: two cameras when the capture
            has at least six).
        fit, loss, prediction, flow: the groups (:class:`FitConfig`, :class:`LossConfig`,
            :class:`PredictionConfig`, :class:`FlowConfig`).
        subdivide: midpoint subdivisions of the template for the Gaussians (4^k splats per face,
            attached at fixed barycentric positions, so gradients still reach the template
            vertices). One flat colour per coarse face cannot show texture finer than the mesh.
        opacity: every splat's opacity (fixed unless ``fit.lr_opacity`` > 0): an opaque surface.
        antialiased: render with the mass-conserving low-pass (:func:`physavatar.splat.rasterize`).
            The plain 3DGS low-pass widens the silhouette of a surface of sub-pixel splats and
            the fit shrinks the garment to undo it.
        splat_backend: the Gaussian rasterizer of the fit (:func:`physavatar.splat.rasterize`):
            "auto" (gsplat's CUDA kernels where CUDA and gsplat are present, else the numba
            kernels), "numba", "gsplat" or "torch" (the dense twin, slow). gsplat renders in
            float32 with atomics in its backward pass, so its runs match a CPU run only to its
            documented edge differences and are not bit-reproducible (docs/splatting.md).
        threads: numba and torch threads during the fit (1 is fastest on a small machine: the
            per-view work at these image sizes is too small to pay for thread start-up).
        seed: torch seed (the fit itself uses no randomness; kept for reproducibility).
    """

    n_frames: int | None = option(None, "track only the first N frames", flag="--frames", hash=False)
    holdout: tuple[str, ...] | None = option(None, "cameras excluded from fitting, CAM,CAM ('' for none; default: two)",
                                             parse=camera_list)
    fit: FitConfig = field(default_factory=FitConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    prediction: PredictionConfig = field(default_factory=PredictionConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    subdivide: int = setting(0)
    opacity: float = setting(0.99)
    antialiased: bool = setting(True)
    splat_backend: str = option("auto", "Gaussian rasterizer: auto (gsplat on CUDA, else numba), numba, gsplat or torch",
                                choices=("auto", "numba", "gsplat", "torch"), check=_backend_problem)
    threads: int = setting(1)
    seed: int = setting(0)


def pipeline_config(track_frames: int | None, holdout: tuple[str, ...] | None = None) -> TrackConfig:
    """The config ``physavatar run`` tracks with: the defaults, ``track_frames`` frames (None: all),
    ``holdout`` cameras held out (None: the default rule)."""
    return TrackConfig(n_frames=track_frames, holdout=holdout)


def second_pass_config(track_frames: int | None, holdout: tuple[str, ...] | None = None) -> TrackConfig:
    """The config of ``physavatar run --track-passes 2``'s second tracking pass (the paper's loop;
    its material, fit-physics' on the first pass, is the stage's ``material`` input): the physics
    step's rest shape the equilibrium one (``prediction.rest_shape``), and the bending terms of the
    lifts holding the step's hinges (``flow.bend_reference`` "physics"). Session 37 (docs/tracking.md,
    "Issue 22, session 37"): neither helps alone; together, with the material of session 36's
    fit, the foreign skirt 5.08 -> 4.18 mm, the tops 0.632 -> 0.577 and 2.835 -> 2.353 mm, the demo's
    48 frames 0.985 -> 0.881 mm."""
    base = pipeline_config(track_frames, holdout)
    return replace(base, prediction=replace(base.prediction, rest_shape="equilibrium"),
                   flow=replace(base.flow, bend_reference="physics"))
