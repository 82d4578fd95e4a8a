"""The differentiable scene of the fit: the lights it starts from, the inverse renderer (loss and
gradients w.r.t. texture and light intensities), and the light values it fits."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ...camera import Camera
from ...capture import Capture
from ...errors import PhysavatarError
from ...render import (
    Ambient,
    AreaLight,
    EnvMap,
    PointLight,
    RenderResult,
    SceneSpec,
    SunLight,
    differentiable_scene,
    make_sensor,
    mitsuba,
)
from ...render.avatar import AvatarMeshes
from ...render.lights import load_lights
from .config import AppearanceConfig
from .data import AppearanceData, load_target


def initial_lights(cfg: AppearanceConfig, capture: Capture, lighting: str | Path | None = None) -> list:
    """The lights the fit starts from: ``Ambient(ambient_init)`` (the paper, A.4.1), or for
    ``studio`` the known studio lights (``lighting`` or ``ground_truth/lighting.json``)."""
    if cfg.light == "ambient":
        return [Ambient((cfg.ambient_init,) * 3)]
    if cfg.light == "env":  # a uniform map: the ambient start; fitted by .envlight
        from .envlight import ENV_SHAPE

        return [EnvMap(np.full(ENV_SHAPE + (3,), cfg.ambient_init, np.float32))]
    path = Path(lighting) if lighting is not None else (capture.root / "ground_truth" / "lighting.json")
    if not path.is_file():
        raise PhysavatarError(path, "light model 'studio' needs the studio's lights (a lighting.json; pass --lighting)")
    lights = load_lights(path)
    if sum(isinstance(l, Ambient) for l in lights) == 0:
        lights = [Ambient((cfg.ambient_init,) * 3)] + lights
    return lights


class InverseRenderer:
    """One differentiable Mitsuba scene of the avatar whose vertex positions are swapped per
    frame; renders the shared texture and lights and returns loss and gradients.

    The body and the garment are separate meshes (one- and two-sided) sampling one atlas; the
    same Dr.Jit texture tensor is assigned to both bitmaps, so its gradient sums both.
    """

    def __init__(self, meshes: AvatarMeshes, rest_vertices: np.ndarray, texture: np.ndarray, lights: list,
                 max_depth: int = 3):
        self.mi = mitsuba()
        self.meshes = meshes
        self.lights = list(lights)
        spec = SceneSpec(meshes=meshes.specs(rest_vertices, texture), lights=self.lights, max_depth=max_depth)
        self.scene, self.params, self.keys = differentiable_scene(spec)
        self.ambient_key = self.keys.ambient
        area = [l.name for l in self.lights if isinstance(l, (AreaLight, PointLight, SunLight))]
        self.key_name = area[0] if area else None
        self.key_key = self.keys.emitters[self.key_name] if self.key_name else None
        self._frame_vertices_id = None
        self._sensors: dict = {}

    def set_vertices(self, vertices: np.ndarray, tag=None) -> None:
        """Move every mesh to template-vertex positions ``vertices`` [V, 3] (BVH and normals are
        rebuilt by ``params.update``); ``tag`` skips the upload when the frame is unchanged."""
        if tag is not None and tag == self._frame_vertices_id:
            return
        for n in self.meshes.names:
            v = vertices[self.meshes.vertex_maps[n]].astype(np.float32).ravel()
            self.params[f"{n}.vertex_positions"] = self.mi.Float(v)
        self.params.update()
        self._frame_vertices_id = tag

    def set_envmap(self, image: np.ndarray) -> None:
        """Replace the scene's environment map by ``image`` [H, W, 3] (linear radiance, the map's
        own shape; Mitsuba keeps it with one wrapped column on either side)."""
        name = next((l.name for l in self.lights if isinstance(l, EnvMap)), None)
        if name is None:
            raise ValueError("the scene has no environment map")
        img = np.asarray(image, np.float32)
        padded = np.concatenate([img[:, -1:], img, img[:, :1]], 1)
        self.params[f"{name}.data"] = self.mi.TensorXf(np.ascontiguousarray(padded))
        self.params.update()

    def sensor(self, cam: Camera, spp: int):
        key = (cam.name, cam.width, spp)
        if key not in self._sensors:
            self._sensors[key] = make_sensor(cam, spp)
        return self._sensors[key]

    def _assign(self, texture: np.ndarray, ambient: np.ndarray | None, key: np.ndarray | None, grad: bool):
        import drjit as dr

        mi = self.mi
        T = mi.TensorXf(np.ascontiguousarray(texture, np.float32))
        if grad:
            dr.enable_grad(T)
        for n in self.meshes.names:
            self.params[self.keys.reflectance[n]] = T
        A = K = None
        if ambient is not None and self.ambient_key is not None:
            A = mi.Color3f(*[float(x) for x in ambient])
            if grad:
                dr.enable_grad(A)
            self.params[self.ambient_key] = A
        if key is not None and self.key_key is not None:
            K = mi.Color3f(*[float(x) for x in key])
            if grad:
                dr.enable_grad(K)
            self.params[self.key_key] = K
        self.params.update()
        return T, A, K

    def render(self, cam: Camera, texture, ambient=None, key=None, *, spp: int = 8, seed: int = 0) -> RenderResult:
        """Forward render [h, w] (no gradients)."""
        self._assign(texture, ambient, key, grad=False)
        img = np.array(self.mi.render(self.scene, self.params, sensor=self.sensor(cam, spp), spp=spp, seed=seed),
                       dtype=np.float32)
        return RenderResult(rgb=img[..., :3], alpha=img[..., 3])

    def loss_and_grads(self, cam: Camera, target: np.ndarray, mask: np.ndarray, texture, ambient=None, key=None,
                       *, spp: int = 8, seed: int = 0):
        """Masked mean squared error (linear RGB, Eq. 8) and its gradients w.r.t. the texture
        [Ht, Wt, 3], the ambient RGB and the key light RGB (None when not in the scene)."""
        import drjit as dr

        mi = self.mi
        T, A, K = self._assign(texture, ambient, key, grad=True)
        img = mi.render(self.scene, self.params, sensor=self.sensor(cam, spp), spp=spp, seed=seed)
        w = mask.astype(np.float32)[..., None] / (3.0 * max(float(mask.sum()), 1.0))
        diff = img[..., :3] - mi.TensorXf(np.ascontiguousarray(target, np.float32))
        loss = dr.sum(dr.square(diff) * mi.TensorXf(np.ascontiguousarray(np.repeat(w, 3, -1))), axis=None)
        dr.backward(loss)
        gT = np.array(dr.grad(T), np.float64)
        gA = np.array(dr.grad(A), np.float64).reshape(3) if A is not None else None
        gK = np.array(dr.grad(K), np.float64).reshape(3) if K is not None else None
        return float(np.array(loss).ravel()[0]), gT, gA, gK


def light_values(lights: list) -> tuple[np.ndarray | None, np.ndarray | None]:
    amb = next((np.broadcast_to(np.asarray(l.radiance, float), (3,)).copy() for l in lights if isinstance(l, Ambient)),
               None)
    key = None
    for l in lights:
        if isinstance(l, AreaLight):
            key = np.broadcast_to(np.asarray(l.radiance, float), (3,)).copy()
        elif isinstance(l, PointLight):
            key = np.broadcast_to(np.asarray(l.intensity, float), (3,)).copy()
        elif isinstance(l, SunLight):
            key = np.broadcast_to(np.asarray(l.irradiance, float), (3,)).copy()
        if key is not None:
            break
    return amb, key


def with_light_values(lights: list, ambient, key) -> list:
    out, key_done = [], False
    for l in lights:
        if isinstance(l, Ambient) and ambient is not None:
            l = replace(l, radiance=tuple(float(x) for x in ambient))
        elif not key_done and key is not None and isinstance(l, (AreaLight, PointLight, SunLight)):
            attr = {AreaLight: "radiance", PointLight: "intensity", SunLight: "irradiance"}[type(l)]
            l = replace(l, **{attr: tuple(float(x) for x in key)})
            key_done = True
        out.append(l)
    return out


def exposure_scale(renderer: InverseRenderer, data: AppearanceData, texture, ambient, key, cfg: AppearanceConfig,
                   n_views: int = 4) -> float:
    """Least-squares factor s minimising Σ‖I − s·R‖² over a few training views (R rendered with
    ``texture`` and the lights). Image radiance is linear in the texture, so s·texture (or
    s·lights) is the best global rescaling of the current state."""
    rng = np.random.default_rng(cfg.seed + 7)
    num = den = 0.0
    for j in range(n_views):
        ti = int(rng.integers(len(data.frames)))
        cam = data.cameras[int(rng.integers(len(data.cameras)))]
        target, mask = load_target(data.capture, cam, data.frames[ti], cfg.scale, cfg.erode_px)
        renderer.set_vertices(data.vertices[ti], tag=ti)
        r = renderer.render(cam.scaled(cfg.scale), texture, ambient, key, spp=cfg.spp, seed=10_000 + j).rgb
        num += float((target[mask] * r[mask]).sum())
        den += float((r[mask] ** 2).sum())
    return num / den if den > 0 else 1.0
