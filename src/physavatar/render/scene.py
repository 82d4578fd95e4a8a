"""Scenes as data, and rendering them from ``Camera`` views.

A :class:`SceneSpec` (meshes + lights) becomes one Mitsuba scene dict in :func:`scene_dict`, the
only place where scenes are assembled. Cameras are not part of the scene: each render passes
its own sensor (``sensor.make_sensor``), so one loaded scene serves every view of a frame.

Images: ``RenderResult.rgb`` is linear radiance with the background black (every emitter is
hidden from camera rays, so environment maps and light panels light the scene without being
seen), i.e. colour premultiplied by coverage; ``RenderResult.alpha`` is the fraction of each
pixel covered by the meshes (box filter: each sample counts only in its own pixel). A
composite over a background is ``rgb + (1 - alpha) * background``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from physavatar.camera import Camera

from .backend import mitsuba
from .image import alpha_to_uint8, linear_to_srgb8
from .lights import Ambient, AreaLight, EnvMap, Light, PointLight, SunLight
from .mesh import MeshSpec, to_mitsuba_mesh
from .sensor import make_sensor


@dataclass(frozen=True)
class SceneSpec:
    """What to render: diffuse meshes (body, garments) and lights.

    Attributes:
        meshes: meshes with distinct names.
        lights: any of ``Ambient``, ``EnvMap``, ``PointLight``, ``AreaLight``, ``SunLight``, with
            distinct names (two lights of one type need explicit names).
        max_depth: Mitsuba path depth: 2 = direct light only, 3 = plus one diffuse
            interreflection (the default; garment-on-body bounce light), -1 = unbounded.
    """

    meshes: Sequence[MeshSpec] = field(default_factory=tuple)
    lights: Sequence[Light] = field(default_factory=tuple)
    max_depth: int = 3

    def __post_init__(self) -> None:
        object.__setattr__(self, "meshes", tuple(self.meshes))
        object.__setattr__(self, "lights", tuple(self.lights))
        names = [m.name for m in self.meshes] + [l.name for l in self.lights]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"scene names must be unique, repeated: {dupes}")
        for light in self.lights:
            if not isinstance(light, (Ambient, EnvMap, PointLight, AreaLight, SunLight)):
                raise TypeError(f"unknown light {light!r}")
        if sum(isinstance(l, (Ambient, EnvMap)) for l in self.lights) > 1:
            raise ValueError("at most one Ambient or EnvMap per scene (Mitsuba allows one environment emitter)")

    def mesh(self, name: str) -> MeshSpec:
        for m in self.meshes:
            if m.name == name:
                return m
        raise KeyError(f"no mesh named {name!r} (have {[m.name for m in self.meshes]})")


def integrator_dict(max_depth: int = 3, *, differentiable: bool = False) -> dict:
    """Path tracer; ``prb`` (path replay backpropagation) when gradients are needed.

    ``hide_emitters`` makes camera rays pass through emitters: the background stays black and
    alpha counts only the meshes (light panels included in the scene stay out of the masks).
    ``prb`` differentiates shading (textures, lights), not silhouettes, which is what the
    appearance stage optimizes; the forward image is the same estimator as ``path``.
    """
    return {"type": "prb" if differentiable else "path", "max_depth": int(max_depth), "hide_emitters": True}


def scene_dict(spec: SceneSpec, *, differentiable: bool = False) -> dict:
    """The Mitsuba scene dict of ``spec`` (meshes as in-memory ``mi.Mesh`` objects)."""
    out: dict = {"type": "scene", "integrator": integrator_dict(spec.max_depth, differentiable=differentiable)}
    for m in spec.meshes:
        out[m.name] = to_mitsuba_mesh(m)
    for light in spec.lights:
        out[light.name] = light.to_dict()
    return out


def load_scene(spec: SceneSpec, *, differentiable: bool = False):
    """``mi.Scene`` of ``spec`` (see :func:`scene_dict`)."""
    return mitsuba().load_dict(scene_dict(spec, differentiable=differentiable))


@dataclass(frozen=True)
class RenderResult:
    """One rendered view.

    Attributes:
        rgb: [H, W, 3] float32 linear radiance, black background (premultiplied by coverage).
        alpha: [H, W] float32 coverage of the meshes in [0, 1].
    """

    rgb: np.ndarray
    alpha: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """[H, W] bool, pixels more than half covered."""
        return self.alpha > 0.5

    def srgb8(self, background=0.0) -> np.ndarray:
        """[H, W, 3] uint8 sRGB image composited over a linear ``background`` colour."""
        bg = np.broadcast_to(np.asarray(background, dtype=np.float32), (3,))
        return linear_to_srgb8(self.rgb + (1.0 - self.alpha[..., None]) * bg)

    def alpha8(self) -> np.ndarray:
        """[H, W] uint8 mask (255 = fully covered)."""
        return alpha_to_uint8(self.alpha)


def render(scene, camera: Camera, *, spp: int = 16, seed: int = 0) -> RenderResult:
    """Render one view.

    Args:
        scene: a :class:`SceneSpec` (loaded here) or an ``mi.Scene`` from :func:`load_scene`
            (load once, render many views).
        camera: OpenCV camera; the image has its width and height.
        spp: samples per pixel (alpha is quantized to multiples of 1 / spp).
        seed: sampler seed; the same scene, camera, spp and seed give the same image.
    Returns:
        :class:`RenderResult` at ``camera``'s resolution.
    """
    mi = mitsuba()
    if isinstance(scene, SceneSpec):
        scene = load_scene(scene)
    sensor = make_sensor(camera, spp)
    img = np.array(mi.render(scene, sensor=sensor, spp=int(spp), seed=int(seed)), dtype=np.float32)
    if img.shape != (camera.height, camera.width, 4):
        raise RuntimeError(f"Mitsuba returned {img.shape}, expected ({camera.height}, {camera.width}, 4)")
    return RenderResult(rgb=np.ascontiguousarray(img[..., :3]), alpha=np.ascontiguousarray(img[..., 3]))


def render_views(spec_or_scene, cameras: Sequence[Camera], *, spp: int = 16, seed: int = 0) -> list[RenderResult]:
    """Render every camera of one frame from a single loaded scene (seed ``seed + i`` for view i,
    so views do not share noise patterns)."""
    scene = load_scene(spec_or_scene) if isinstance(spec_or_scene, SceneSpec) else spec_or_scene
    return [render(scene, cam, spp=spp, seed=seed + i) for i, cam in enumerate(cameras)]


@dataclass(frozen=True)
class ParamKeys:
    """``mi.traverse`` key names of the quantities the appearance stage optimizes.

    Attributes:
        reflectance: mesh name -> key of its reflectance: ``"<mesh>.bsdf.reflectance.data"``
            (texture, [Ht, Wt, 3] tensor), ``"<mesh>.vertex_color"`` (flat [3 V] buffer) or
            ``"<mesh>.bsdf.reflectance.value"`` (constant colour); ``twosided`` meshes have
            ``brdf_0`` after ``bsdf``.
        ambient: key of the ``Ambient`` radiance (``"<name>.radiance.value"``) or of the
            ``EnvMap`` scale (``"<name>.scale"``), None without either.
        emitters: light name -> key of its colour/strength parameter, for every light.
    """

    reflectance: dict[str, str]
    ambient: str | None
    emitters: dict[str, str]


def param_keys(spec: SceneSpec) -> ParamKeys:
    """Key names of ``spec``'s optimizable parameters (they follow from the scene dict)."""
    reflectance = {}
    for m in spec.meshes:
        bsdf = f"{m.name}.bsdf.brdf_0" if m.twosided else f"{m.name}.bsdf"
        reflectance[m.name] = {
            "texture": f"{bsdf}.reflectance.data",
            "vertex_color": f"{m.name}.vertex_color",
            "constant": f"{bsdf}.reflectance.value",
        }[m.material]
    emitters = {}
    ambient = None
    for light in spec.lights:
        if isinstance(light, Ambient):
            key = f"{light.name}.radiance.value"
            ambient = key
        elif isinstance(light, EnvMap):
            key = f"{light.name}.scale"
            ambient = key
        elif isinstance(light, AreaLight):
            key = f"{light.name}.emitter.radiance.value"
        elif isinstance(light, PointLight):
            key = f"{light.name}.intensity.value"
        else:
            key = f"{light.name}.irradiance.value"
        emitters[light.name] = key
    return ParamKeys(reflectance=reflectance, ambient=ambient, emitters=emitters)


def differentiable_scene(spec: SceneSpec):
    """Load ``spec`` for inverse rendering.

    Returns:
        (scene, params, keys): the ``mi.Scene`` (``prb`` integrator), its ``mi.traverse``
        parameters, and :class:`ParamKeys`. A fitting loop then reads like the math::

            scene, params, keys = differentiable_scene(spec)
            sensor = make_sensor(camera, spp=8)
            k = keys.reflectance["garment"]
            dr.enable_grad(params[k]); params.update()
            img = mi.render(scene, params, sensor=sensor, spp=8, seed=i)
            loss = dr.mean(dr.square(img[..., :3] - target)); dr.backward(loss)
            grad = dr.grad(params[k])
    """
    mi = mitsuba()
    scene = load_scene(spec, differentiable=True)
    params = mi.traverse(scene)
    keys = param_keys(spec)
    wanted = list(keys.reflectance.values()) + list(keys.emitters.values())
    missing = [k for k in wanted if k not in params]
    if missing:  # the key scheme above is derived from Mitsuba's naming; fail loudly if it moves
        raise RuntimeError(f"Mitsuba scene lacks expected parameters {missing}")
    return scene, params, keys
