"""The appearance stage's settings: :class:`AppearanceConfig` (its fields with a command-line
option carry the flag and help, :mod:`physavatar.stages.base`), the ``--quick`` preset and the
settings ``physavatar run`` uses."""

from __future__ import annotations

from dataclasses import dataclass, replace

from ...errors import PhysavatarError
from ..base import option, setting, to_dict

LIGHT_MODES = ("ambient", "studio", "env")
INIT_MODES = ("project", "faces")
MESH_SOURCES = ("tracked", "gt")


def _camera_list(text: str) -> tuple[str, ...] | None:
    """'cam00, cam01' -> ('cam00', 'cam01'); an empty list means all cameras (None)."""
    return tuple(c.strip() for c in text.split(",") if c.strip()) or None


@dataclass(frozen=True)
class AppearanceConfig:
    """Everything that defines an appearance fit (saved as config.json).

    Attributes:
        meshes: ``"tracked"`` (the tracking output's meshes and Gaussian colours) or ``"gt"``
            (``ground_truth/meshes.npz`` of a synthetic capture).
        light: ``"ambient"`` (the paper: texture + global ambient L_a), ``"studio"`` (texture +
            ambient + the known key light's intensity) or ``"env"`` (texture + a smooth
            environment map fitted in closed form before the projection, :mod:`.envlight`).
        iterations: Adam steps (A.4: 2000). Not part of the resume check, so a run can be extended.
        lr, lr_decay, lr_decay_every: Adam learning rate, halved every 500 steps (A.4).
        spp: samples per pixel while fitting (A.4: 8); final_spp for the preview renders (128).
        texture_size: atlas resolution (square); the official code uses 2048² on a GPU.
        scale: image resolution factor w.r.t. the capture (CPU budget).
        batch: (frame, camera) views per step (A.4: 1).
        erode_px: foreground mask erosion in capture pixels (A.4: 2).
        max_depth: path depth (3 = direct + one bounce, as the synthetic captures are rendered).
        ambient_init: initial L_a (A.4: unit radiance).
        fit_light: optimize the light intensities (False: keep them at their initial values).
        light_lr: Adam learning rate of the light intensities (None: ``lr``).
        cameras: training camera names (None: all cameras of the capture).
        frame_stride: use every k-th frame (the paper uses 200 of ~2000 frames).
        init_frame_stride: every k-th frame for the initial per-face colours.
        checkpoint_every: steps between checkpoints (and log flushes).
        seed: (frame, camera) sampling and Monte Carlo seeds.
        init: how T_0 is made: ``"project"`` (every texel looked up in the views that see it,
            shading divided out in closed form, unseen texels inpainted along the surface;
            :mod:`.project`) or ``"faces"`` (the paper: per-face colours averaged over frames).
        project_views: at most this many (frame, camera) views for ``"project"`` (frames spread
            evenly over the sequence, every training camera).
        project_spp: samples per pixel of the irradiance renders of ``"project"``.
        env_lobes, env_views, env_spp: the ``env`` light: lobes of its basis (besides the
            constant map), training views its fit uses (frames spread over the sequence, cameras
            in turn) and samples per pixel of its basis renders.
        min_size: the fit never renders images smaller than this (pixels, the larger side):
            ``scale`` is raised to ``min_size / size`` for small captures (a 256 px capture is
            fitted at full resolution; at half of it each texel gets a quarter of the pixels).
        project_passes: 1, or more for iterative back-projection passes after the first
            (``"project"``; each renders every projection view once more).
        prior_views: weight of each texel's prior (its face's colour, inpainted where unseen),
            in views (``"project"``).
    """

    meshes: str = option("tracked", "tracked, or gt (ground_truth/meshes.npz of a synthetic capture)",
                         choices=MESH_SOURCES)
    light: str = option("ambient", "ambient (the paper: texture + L_a), studio (+ the known key light's intensity) or "
                        "env (+ a smooth environment map fitted with the texture)")
    iterations: int = option(2000, "Adam steps (paper: 2000)", hash=False)
    lr: float = option(0.01, "Adam learning rate, halved every --decay-every steps")
    lr_decay: float = setting(0.5)
    lr_decay_every: int = option(500, "", flag="--decay-every")
    spp: int = option(8, "samples per pixel while fitting (paper: 8)")
    final_spp: int = option(128, "samples per pixel of the preview renders")
    texture_size: int = option(512, "atlas resolution in texels")
    scale: float = option(1.0, "image resolution factor in (0, 1]")
    batch: int = option(1, "random (frame, camera) views per step")
    erode_px: int = setting(2)
    max_depth: int = setting(3)
    ambient_init: float = setting(1.0)
    fit_light: bool = option(True, "fit the light, or keep it at its initial value (--fix-light)",
                             flag="--fit-light/--fix-light")
    light_lr: float | None = setting(None)
    cameras: tuple[str, ...] | None = option(None, "training cameras CAM,CAM (default: all)", parse=_camera_list)
    frame_stride: int = option(1, "fit every k-th frame")
    init_frame_stride: int = setting(1)
    checkpoint_every: int = setting(50, hash=False)
    seed: int = option(0, "")
    init: str = option("project", "initial texture: project (texels looked up in the views that see them, shading "
                       "divided out) or faces (the paper: per-face colours)", choices=INIT_MODES)
    project_views: int = setting(48)
    project_spp: int = setting(16)
    prior_views: float = setting(0.5)
    project_passes: int = setting(1)
    min_size: int = setting(256)
    env_lobes: int = setting(12)
    env_views: int = setting(12)
    env_spp: int = setting(8)

    def __post_init__(self) -> None:
        if self.light not in LIGHT_MODES:
            raise PhysavatarError(None, f"light model {self.light!r} is not one of {', '.join(LIGHT_MODES)}")
        if self.init not in INIT_MODES:
            raise PhysavatarError(None, f"init {self.init!r} is not one of {', '.join(INIT_MODES)}")
        if self.meshes not in MESH_SOURCES:
            raise PhysavatarError(None, f"meshes must be 'tracked' or 'gt', got {self.meshes!r}")
        checks = [("iterations", self.iterations >= 0), ("lr", self.lr > 0), ("spp", self.spp >= 1),
                  ("final_spp", self.final_spp >= 1), ("texture_size", 8 <= self.texture_size <= 8192),
                  ("scale", 0 < self.scale <= 1), ("batch", self.batch >= 1), ("erode_px", self.erode_px >= 0),
                  ("lr_decay_every", self.lr_decay_every >= 1), ("frame_stride", self.frame_stride >= 1),
                  ("init_frame_stride", self.init_frame_stride >= 1), ("checkpoint_every", self.checkpoint_every >= 1),
                  ("ambient_init", self.ambient_init > 0), ("project_views", self.project_views >= 1),
                  ("project_spp", self.project_spp >= 1), ("prior_views", self.prior_views >= 0),
                  ("project_passes", self.project_passes >= 1),
                  ("min_size", self.min_size >= 1), ("env_lobes", self.env_lobes >= 0),
                  ("env_views", self.env_views >= 1), ("env_spp", self.env_spp >= 1)]
        for name, ok in checks:
            if not ok:
                raise PhysavatarError(None, f"appearance config: {name}={getattr(self, name)!r} is out of range")
        if self.cameras is not None:
            object.__setattr__(self, "cameras", tuple(self.cameras))

    def to_dict(self) -> dict:
        """JSON-ready fields (``cameras`` as a list); ``AppearanceConfig(**d)`` gives it back."""
        return to_dict(self)


def fit_scale(config: AppearanceConfig, width: int, height: int) -> float:
    """The image scale the fit renders at for a capture of ``width`` × ``height`` pixels:
    ``config.scale``, raised so that the larger side is at least ``config.min_size`` (at most 1)."""
    return float(min(1.0, max(config.scale, config.min_size / max(width, height, 1))))


# The Adam steps' learning rate of `run` and `--quick`. Each step renders one random view at 8
# spp, so a texel's gradient is mostly Monte Carlo and capture noise, and Adam (normalised per
# texel) moves every texel about lr per step whatever its signal: a random walk whose size grows
# with lr. At 0.02 it left a texel-scale grain on every surface (foreign print top: T₀ 31.0 dB on
# the held-out cameras, after the steps 28.0 dB, LPIPS 0.011 -> 0.040); at 0.005 the steps keep
# what they add (sharper plaid, LPIPS) and lose little (docs/appearance.md).
RUN_LR = 0.005


def quick_preset(config: AppearanceConfig) -> AppearanceConfig:
    """``--quick``: a few-minute CPU budget (at most 200 iterations at lr at most ``RUN_LR``
    halved at least every 50 steps, half-resolution images, 32-spp previews, initial colours
    from every 4th frame); settings already below these budgets are kept."""
    return replace(config, iterations=min(config.iterations, 200), scale=min(config.scale, 0.5),
                   final_spp=min(config.final_spp, 32), lr=min(config.lr, RUN_LR),
                   lr_decay_every=min(config.lr_decay_every, 50), init_frame_stride=4)


def pipeline_config(quick: bool = False) -> AppearanceConfig:
    """The settings ``physavatar run`` fits with: the ``env`` light (a smooth environment map
    fitted with the albedo: the captures' lights are not known, and light with a direction has
    nowhere else to go than the texture) and lr ``RUN_LR``, with ``--quick``'s preset or the CPU
    schedule (300 iterations, lr halved every 100, half-resolution images, 64-spp previews;
    docs/appearance.md)."""
    if quick:
        return replace(quick_preset(AppearanceConfig()), light="env")
    return AppearanceConfig(light="env", iterations=300, scale=0.5, lr=RUN_LR, lr_decay_every=100, final_spp=64)
