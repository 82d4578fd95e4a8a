"""Mitsuba 3 rendering: scenes as data, OpenCV cameras, lights, RGB + coverage images.

Conventions and lighting options: docs/rendering.md. Entry points::

    spec = SceneSpec(meshes=[MeshSpec("body", V, F, colors=C)], lights=soft_studio())
    result = render(spec, camera, spp=16, seed=0)   # result.rgb [H, W, 3], result.alpha [H, W]
"""

from .backend import choose_variant, mitsuba, variant
from .image import alpha_to_uint8, linear_to_srgb, linear_to_srgb8, read_png, srgb_to_linear, to_uint8, write_png
from .lights import (
    LIGHT_NAMES,
    Ambient,
    AreaLight,
    EnvMap,
    Light,
    PointLight,
    SunLight,
    envmap_directions,
    light_center,
    light_to_json,
    load_lights,
    named_lights,
    save_lights,
    sky_envmap,
    soft_studio,
)
from .mesh import MeshSpec, bsdf_dict, to_mitsuba_mesh
from .scene import (
    ParamKeys,
    RenderResult,
    SceneSpec,
    differentiable_scene,
    load_scene,
    param_keys,
    render,
    render_views,
    scene_dict,
)
from .sensor import make_sensor, sensor_dict
from .sheet import contact_sheet

__all__ = [
    "LIGHT_NAMES",
    "Ambient",
    "AreaLight",
    "EnvMap",
    "Light",
    "MeshSpec",
    "ParamKeys",
    "PointLight",
    "RenderResult",
    "SceneSpec",
    "SunLight",
    "alpha_to_uint8",
    "bsdf_dict",
    "choose_variant",
    "contact_sheet",
    "differentiable_scene",
    "envmap_directions",
    "light_center",
    "light_to_json",
    "linear_to_srgb",
    "linear_to_srgb8",
    "load_lights",
    "load_scene",
    "make_sensor",
    "mitsuba",
    "named_lights",
    "param_keys",
    "read_png",
    "render",
    "render_views",
    "save_lights",
    "scene_dict",
    "sensor_dict",
    "sky_envmap",
    "soft_studio",
    "srgb_to_linear",
    "to_mitsuba_mesh",
    "to_uint8",
    "variant",
    "write_png",
]
