"""Light sources as plain data, each turned into a Mitsuba emitter dict by ``to_dict()``.

Units are Mitsuba's (linear RGB): radiance [W/(m²·sr)] for ambient, environment and area lights,
intensity [W/sr] for point lights, irradiance [W/m²] for the sun. A white one-sided diffuse
surface of reflectance ρ under a constant ambient radiance L, with nothing else in view of it,
has radiance ρ·L (the cosine-weighted hemisphere integrates to π, cancelled by the 1/π of the
Lambertian BRDF).

Environment maps are equirectangular (latitude-longitude) images in the world frame (z up):
row 0 is the zenith (+z), the last row the nadir; the centre column looks along +x and the
column at one quarter of the width along +y (Blender's convention, so polyhaven HDRIs look the
same as there). Mitsuba's envmap is y-up with its seam at -z; ``ENVMAP_TO_WORLD`` maps one onto
the other, and ``rotation_deg`` turns the map about +z (counter-clockwise seen from above).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from ..files import read_json, write_json_atomic
from .backend import mitsuba

# Columns: world images of Mitsuba's envmap-local x, y, z axes. Mitsuba's lookup is
# u = atan2(d_x, -d_z) / 2π, v = acos(d_y) / π in local coordinates, so local +y (v = 0) must be
# world +z (row 0 = zenith) and local +z (u = 1/2) world +x; local +x (u = 1/4) is then world +y.
ENVMAP_TO_WORLD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _rgb(x) -> list[float]:
    v = np.broadcast_to(np.asarray(x, dtype=np.float64), (3,))
    if not np.isfinite(v).all() or (v < 0).any():
        raise ValueError(f"light colour must be finite and non-negative, got {x!r}")
    return [float(c) for c in v]


def _unit(x, what: str) -> np.ndarray:
    v = np.asarray(x, dtype=np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"{what} must be a non-zero vector, got {x!r}")
    return v / n


def _frame(normal: np.ndarray) -> np.ndarray:
    """[3, 3] rotation whose third column is ``normal`` (the first two span the plane)."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    a = np.cross(helper, normal)
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    return np.column_stack([a, b, normal])


@dataclass(frozen=True)
class Ambient:
    """Constant radiance from every direction (Mitsuba ``constant``): the ambient light that the
    inverse-rendering stage fits together with the texture."""

    radiance: float | tuple[float, float, float] = 1.0
    name: str = "ambient"

    def to_dict(self) -> dict:
        return {"type": "constant", "radiance": {"type": "rgb", "value": _rgb(self.radiance)}}


@dataclass(frozen=True)
class EnvMap:
    """HDR environment map: a file (.hdr / .exr) or a [H, W, 3] linear float array."""

    image: str | os.PathLike | np.ndarray = field(repr=False)
    scale: float = 1.0
    rotation_deg: float = 0.0
    name: str = "envmap"

    def to_dict(self) -> dict:
        mi = mitsuba()
        c, s = np.cos(np.radians(self.rotation_deg)), np.sin(np.radians(self.rotation_deg))
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        to_world = np.eye(4)
        to_world[:3, :3] = rz @ ENVMAP_TO_WORLD
        out = {"type": "envmap", "scale": float(self.scale), "to_world": mi.ScalarTransform4f(to_world.tolist())}
        if isinstance(self.image, np.ndarray):
            img = np.ascontiguousarray(self.image, dtype=np.float32)
            if img.ndim != 3 or img.shape[2] != 3 or not np.isfinite(img).all() or (img < 0).any():
                raise ValueError(f"envmap array must be finite, non-negative [H, W, 3], got {img.shape}")
            out["bitmap"] = mi.Bitmap(img)
        else:
            path = Path(self.image)
            if not path.is_file():
                raise FileNotFoundError(f"environment map not found: {path}")
            out["filename"] = str(path)
        return out


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light at ``position`` with ``intensity`` [W/sr]."""

    position: tuple[float, float, float]
    intensity: float | tuple[float, float, float] = 10.0
    name: str = "point"

    def to_dict(self) -> dict:
        return {
            "type": "point",
            "position": [float(x) for x in np.asarray(self.position, dtype=np.float64).reshape(3)],
            "intensity": {"type": "rgb", "value": _rgb(self.intensity)},
        }


@dataclass(frozen=True)
class AreaLight:
    """One-sided rectangular light panel of ``size`` = (width, height) metres centred at
    ``center``, emitting ``radiance`` towards ``target`` from its front face.

    The panel is black (it reflects nothing) and the renderer hides it from camera rays, so it
    lights the scene without showing up in images or masks; it still blocks light behind it.
    """

    center: tuple[float, float, float]
    target: tuple[float, float, float]
    size: tuple[float, float] = (1.0, 1.0)
    radiance: float | tuple[float, float, float] = 5.0
    name: str = "area"

    def to_dict(self) -> dict:
        mi = mitsuba()
        c = np.asarray(self.center, dtype=np.float64).reshape(3)
        n = _unit(np.asarray(self.target, dtype=np.float64) - c, "AreaLight target - center")
        to_world = np.eye(4)
        # Mitsuba's rectangle spans [-1, 1]² in its local xy plane with normal +z.
        to_world[:3, :3] = _frame(n) @ np.diag([0.5 * self.size[0], 0.5 * self.size[1], 1.0])
        to_world[:3, 3] = c
        return {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f(to_world.tolist()),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": _rgb(self.radiance)}},
        }


@dataclass(frozen=True)
class SunLight:
    """Directional light from the direction ``to_sun`` (pointing from the scene to the sun) with
    ``irradiance`` [W/m²] on a surface facing it. Casts hard shadows."""

    to_sun: tuple[float, float, float] = (0.3, -0.5, 0.8)
    irradiance: float | tuple[float, float, float] = 3.0
    name: str = "sun"

    def to_dict(self) -> dict:
        d = -_unit(self.to_sun, "SunLight.to_sun")  # Mitsuba wants the direction light travels
        return {
            "type": "directional",
            "direction": [float(x) for x in d],
            "irradiance": {"type": "rgb", "value": _rgb(self.irradiance)},
        }


Light = Ambient | EnvMap | PointLight | AreaLight | SunLight


def envmap_directions(height: int, width: int) -> np.ndarray:
    """[H, W, 3] unit world direction of each texel centre of an equirectangular map (module doc)."""
    theta = (np.arange(height) + 0.5) / height * np.pi  # polar angle from +z
    u = (np.arange(width) + 0.5) / width
    phi = np.pi * (1.0 - 2.0 * u)  # u = 1/2 -> +x, u = 1/4 -> +y (azimuth pi/2)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack(
        [st * np.cos(phi)[None, :], st * np.sin(phi)[None, :], np.broadcast_to(ct, (height, width))], axis=-1
    )


def sky_envmap(
    height: int = 64,
    width: int = 128,
    *,
    to_sun: tuple[float, float, float] = (0.3, -0.6, 0.75),
    zenith: tuple[float, float, float] = (0.35, 0.55, 1.0),
    horizon: tuple[float, float, float] = (1.0, 0.95, 0.85),
    ground: tuple[float, float, float] = (0.25, 0.22, 0.2),
    sun_radiance: float = 60.0,
    sun_radius_deg: float = 6.0,
) -> np.ndarray:
    """A small sky-like HDR environment as a [H, W, 3] float32 linear array.

    Sky colour blends from ``horizon`` to ``zenith`` with elevation, the lower hemisphere is a
    uniform ``ground``, and a disc of ``sun_radiance`` with a smooth edge sits towards ``to_sun``.
    The sun disc is widened well past the real 0.27° so that a 64×128 map resolves it and the
    shadows it casts stay soft. For tests and demos that must run without the HDRIs in
    ``shared/data/envmaps``.
    """
    d = envmap_directions(height, width)
    z = d[..., 2:3]
    t = np.sqrt(np.clip(z, 0.0, 1.0))
    sky = (1.0 - t) * np.asarray(horizon) + t * np.asarray(zenith)
    img = np.where(z >= 0.0, sky, np.asarray(ground))
    cos_angle = d @ _unit(to_sun, "to_sun")
    angle = np.degrees(np.arccos(np.clip(cos_angle, -1.0, 1.0)))
    disc = np.clip((sun_radius_deg - angle) / (0.3 * sun_radius_deg) + 0.5, 0.0, 1.0)  # linear rim
    img = img + sun_radiance * disc[..., None] * np.array([1.0, 0.95, 0.85])
    return img.astype(np.float32)


def soft_studio(
    target=(0.0, 0.0, 1.0),
    front=(0.0, -1.0, 0.0),
    *,
    ambient: float = 0.35,
    key_radiance: float = 3.0,
    key_size: float = 2.0,
    key_distance: float = 2.5,
    key_elevation_deg: float = 50.0,
) -> list[Light]:
    """Lighting for synthetic captures: ambient plus a large square panel above-front.

    The panel (``key_size`` metres wide, ``key_distance`` from ``target``, raised
    ``key_elevation_deg`` above the horizontal towards ``front``; Anny bodies face -y) casts soft
    self-shadows under the chin, arms and garment folds, which ambient light alone would not.
    """
    target = np.asarray(target, dtype=np.float64)
    f = np.asarray(front, dtype=np.float64)
    f = f - f[2] * np.array([0.0, 0.0, 1.0])
    f = _unit(f, "front (horizontal part)")
    e = np.radians(key_elevation_deg)
    center = target + key_distance * (np.cos(e) * f + np.sin(e) * np.array([0.0, 0.0, 1.0]))
    return [
        Ambient(ambient),
        AreaLight(tuple(center), tuple(target), (key_size, key_size), key_radiance, name="key"),
    ]


# -- lights by name ------------------------------------------------------------------------------

def light_center(vertices: np.ndarray) -> np.ndarray:
    """[3] the point named lights aim at (and orbit cameras circle): the mean of ``vertices``
    [V, 3] in x and y, the middle of their height in z."""
    V = np.asarray(vertices, dtype=np.float64)
    c = V.mean(0)
    c[2] = 0.5 * (V[:, 2].max() + V[:, 2].min())
    return c


def _point_pair(c: np.ndarray) -> list[Light]:
    return [PointLight(tuple(c + [1.2, -1.5, 0.8]), (4.0, 3.0, 2.0), name="point_warm"),
            PointLight(tuple(c + [-1.5, -1.0, 0.3]), (1.0, 1.8, 3.0), name="point_cool"),
            Ambient(0.05)]


# name -> lights(center [3], strength); ``strength`` scales environment maps only.
NAMED_LIGHTS = {
    "studio": lambda c, strength: soft_studio(target=tuple(float(x) for x in c)),
    "ambient": lambda c, strength: [Ambient(1.0)],
    "sky": lambda c, strength: [EnvMap(sky_envmap(), scale=1.0 * strength)],
    "sun": lambda c, strength: [Ambient(0.25), SunLight(to_sun=(0.4, -0.6, 0.7), irradiance=3.0)],
    "point": lambda c, strength: _point_pair(np.asarray(c, dtype=np.float64)),
}

LIGHT_NAMES = ("fitted", *NAMED_LIGHTS)
"""The names :func:`named_lights` knows; any path ending in .hdr or .exr is an environment map."""


def named_lights(name: str, center, *, fitted: list | str | os.PathLike | None = None,
                 strength: float = 1.0) -> list[Light]:
    """The lights called ``name`` (docs/rendering.md, "Lights by name").

    Args:
        name: ``fitted`` (the lights of a fit-appearance ``light.json``), ``studio`` (the
            synthetic captures' :func:`soft_studio` aimed at ``center``), ``ambient`` (uniform
            radiance 1), ``sky`` (the generated :func:`sky_envmap`), ``sun`` (a sun from
            above-front plus ambient fill), ``point`` (a warm and a cool point light beside
            ``center``), or the path of an ``.hdr``/``.exr`` environment map.
        center: [3] where the lights aim (:func:`light_center` of the avatar).
        fitted: the fitted lights, or the ``light.json`` to read them from (only ``fitted``
            uses it).
        strength: scale of the environment maps (``sky`` and files).
    """
    if name == "fitted":
        if isinstance(fitted, (str, os.PathLike)):
            path = Path(fitted)
            if not path.is_file():
                raise PhysavatarError(path.parent, f"has no {path.name} (run fit-appearance, or choose another --light)")
            return load_lights(path)
        if not fitted:
            raise PhysavatarError(None, "light 'fitted' needs fitted lights (a light.json from fit-appearance); "
                                        "choose another --light")
        return list(fitted)
    if name in NAMED_LIGHTS:
        return NAMED_LIGHTS[name](center, strength)
    p = Path(name)
    if p.suffix.lower() in (".hdr", ".exr"):
        if not p.is_file():
            raise PhysavatarError(p, "environment map not found")
        return [EnvMap(str(p), scale=1.0 * strength)]
    raise PhysavatarError(None, f"unknown light {name!r}: choose {', '.join(LIGHT_NAMES)} or an .hdr/.exr file")


# -- lights as JSON ------------------------------------------------------------------------------

MAX_INLINE_ENVMAP = 32 * 64 * 3
_LIGHT_TYPES = {cls.__name__: cls for cls in (Ambient, EnvMap, PointLight, AreaLight, SunLight)}


def light_to_json(light: Light) -> dict:
    """``{"type": class name, field: value, ...}`` with tuples as lists. An environment map is
    written by its file path, or, held as a small array (a fitted map, at most
    ``MAX_INLINE_ENVMAP`` values), as nested lists [H][W][3]."""
    d = {"type": type(light).__name__}
    for f in fields(light):
        v = getattr(light, f.name)
        if isinstance(v, np.ndarray):
            if v.size > MAX_INLINE_ENVMAP:
                raise ValueError(f"light {light.name!r}: an array environment map of {v.size} values is too large "
                                 f"for JSON (at most {MAX_INLINE_ENVMAP}); save it as .exr and give its path")
            v = np.asarray(v, np.float64).round(6).tolist()
        if isinstance(v, os.PathLike):
            v = str(v)
        elif isinstance(v, (tuple, list)):
            v = np.asarray(v).tolist()
        elif isinstance(v, np.generic):
            v = v.item()
        d[f.name] = v
    return d


def save_lights(path: str | os.PathLike, lights, extra: dict | None = None) -> None:
    """Write ``{"lights": [...], **extra}`` to ``path`` atomically (the format of ``light.json``
    and ``lighting.json``)."""
    write_json_atomic(path, {"lights": [light_to_json(l) for l in lights], **(extra or {})})


def load_lights(path: str | os.PathLike) -> list[Light]:
    """The lights of a file written by :func:`save_lights`."""
    path = Path(path)
    out = []
    for l in read_json(path).get("lights", []):
        kind = l.get("type")
        if kind not in _LIGHT_TYPES:
            raise PhysavatarError(path, f"unsupported light type {kind!r}")
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in l.items() if k != "type"}
        if kind == "EnvMap" and isinstance(l.get("image"), list):  # an inline map [H][W][3]
            img = np.asarray(l["image"], np.float32)
            if img.ndim != 3 or img.shape[2] != 3 or not np.isfinite(img).all() or (img < 0).any():
                raise PhysavatarError(path, f"light EnvMap: image must be [H][W][3] finite non-negative values, "
                                            f"got shape {img.shape}")
            kw["image"] = img
        try:
            out.append(_LIGHT_TYPES[kind](**kw))
        except TypeError as e:
            raise PhysavatarError(path, f"light {kind}: {e}") from None
    if not out:
        raise PhysavatarError(path, "no lights")
    return out
