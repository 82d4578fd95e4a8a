"""Relighting (PhysAvatar Sec. 3.3): the fitted texture on one frame's mesh under a new light,
rendered from every capture camera into one contact sheet.

The mesh comes from a capture's ground truth (``ground_truth/meshes.npz``) or a tracking folder
(``tracked.npz``; the cameras then come from the capture named in its ``config.json`` or given
as ``capture``), the lights by name from the one light table of
:func:`physavatar.render.lights.named_lights` (``fitted`` is the fit's ``light.json``), the same
table ``physavatar render`` uses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..capture import load_capture, save_png
from ..data.tracked import FILE as TRACKED, TrackedSequence
from ..errors import PhysavatarError
from ..files import read_json
from ..progress import resolve
from ..render import RenderResult, SceneSpec, contact_sheet, render
from ..render.avatar import AvatarMeshes
from ..render.lights import light_center, named_lights
from .appearance.outputs import FittedAppearance
from .base import option


def relight(mesh_vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray, texture: np.ndarray, camera: Camera,
            light, *, labels: np.ndarray | None = None, spp: int = 128, seed: int = 0, max_depth: int = 3) -> RenderResult:
    """Render a textured avatar under new light.

    Args:
        mesh_vertices: [V, 3] one frame (tracked, simulated or ground truth).
        faces: [F, 3]; face_uvs: [F, 3, 2] the atlas of ``texture``; texture: [H, W, 3] linear albedo.
        camera: OpenCV camera.
        light: a light of ``physavatar.render``, a list of them, or a name of
            :func:`physavatar.render.lights.named_lights` (aimed at :func:`~physavatar.render.lights.light_center`).
        labels: [V] 0 body / >0 garment, to render the body one-sided and garments two-sided
            like the capture (None: one two-sided mesh).
    Returns:
        ``RenderResult`` (rgb linear with black background, alpha).
    """
    V = np.asarray(mesh_vertices, np.float64)
    if isinstance(light, str):
        light = named_lights(light, light_center(V))
    lights = list(light) if isinstance(light, (list, tuple)) else [light]
    m = AvatarMeshes.build(V, np.asarray(faces), np.asarray(face_uvs, np.float64), labels)
    spec = SceneSpec(meshes=m.specs(V, np.asarray(texture, np.float32)), lights=lights, max_depth=max_depth)
    return render(spec, camera, spp=spp, seed=seed)


@dataclass(frozen=True)
class RelightConfig:
    """The ``relight`` command's settings: the light (a name of the light table or an environment
    map file), the frame, samples per pixel, the environment map's strength, the image scale."""

    light: str = option("sky", "fitted, studio, ambient, sky, sun, point, or an .hdr/.exr environment map "
                               "(docs/rendering.md)")
    frame: int | None = option(None, "frame id (default: the first)")
    spp: int = option(128, "")
    strength: float = option(1.0, "environment map scale")
    scale: float = option(1.0, "image resolution factor")


@dataclass
class RelightResult:
    """What ``run`` wrote: the contact sheet ``out`` of ``views`` renders of ``frame``."""

    out: Path
    frame: int
    views: int
    size: tuple[int, int]  # the contact sheet's width, height


def run(source: Path, *, out: Path, config: RelightConfig, texture: Path, capture: Path | None = None,
        progress=None) -> RelightResult:
    """Render frame ``config.frame`` of ``source`` (a capture folder: its ground-truth meshes, or a
    tracking folder) with the fit-appearance folder ``texture``'s texture under ``config.light``
    from every camera of the capture, and write the contact sheet to ``out`` (a PNG)."""
    source, out, texture = Path(source), Path(out), Path(texture)
    if out.suffix.lower() != ".png":
        raise PhysavatarError(None, f"option --out: {out} must end in .png")
    if config.spp < 1 or not (0 < config.scale <= 1):
        raise PhysavatarError(None, "option --spp/--scale: spp >= 1 and scale in (0, 1]")
    fit = FittedAppearance.load(texture)
    if (source / TRACKED).is_file():
        tr = TrackedSequence.load(source, require=("vertices", "frames"))
        V_all, frames = tr.vertices, [int(f) for f in tr.frames]
        if capture is None:
            cfg_path = source / "config.json"
            guess = read_json(cfg_path).get("capture") if cfg_path.is_file() else None
            if not guess:
                raise PhysavatarError(None, "option --capture: needed to find the cameras of a tracking folder")
            capture = Path(guess)
        cap = load_capture(capture)
    else:
        cap = load_capture(source)
        if cap.ground_truth is None or not (cap.ground_truth / "meshes.npz").is_file():
            raise PhysavatarError(source, "no ground_truth/meshes.npz: pass a tracking folder instead")
        V_all, frames = TrackedSequence.load(cap.ground_truth / "meshes.npz").vertices, list(cap.frames)
    f = frames[0] if config.frame is None else config.frame
    if f not in frames:
        raise PhysavatarError(None, f"option --frame: {f} is not one of the frames {frames[0]}..{frames[-1]}")
    V = V_all[frames.index(f)]
    t = cap.template
    if fit.face_uvs.shape != (len(t.faces), 3, 2):
        raise PhysavatarError(texture / "atlas.npz", "the atlas does not match this capture's template")
    light = config.light
    lights = named_lights(light, light_center(V), fitted=fit.lights, strength=config.strength)
    imgs = []
    with resolve(progress).task("relight", total=len(cap.cameras)) as task:
        for cam in cap.cameras:
            r = relight(V, t.faces, fit.face_uvs, fit.texture, cam.scaled(config.scale), lights, labels=t.labels,
                        spp=config.spp)
            imgs.append(r.srgb8())
            task.advance()
    sheet = contact_sheet(imgs, [f"{c.name} {light if len(light) < 20 else Path(light).name}" for c in cap.cameras])
    save_png(out, sheet)
    return RelightResult(out, f, len(imgs), (sheet.shape[1], sheet.shape[0]))
