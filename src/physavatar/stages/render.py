"""``physavatar render``: an animated avatar sequence as PNG frames and an MP4, from capture
cameras or an orbit, under the fitted light or any new one (relighting, paper Sec. 3.3)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera, intrinsics, look_at
from ..data.animated import AnimatedSequence
from ..errors import PhysavatarError
from ..files import write_json_atomic
from ..progress import resolve
from ..render.lights import light_center, named_lights
from .base import option


def orbit_cameras(center, n: int, radius: float = 3.2, height: float = 1.1, width: int = 512,
                  height_px: int = 512, fov_y_deg: float = 40.0, start_deg: float = -90.0) -> list[Camera]:
    """n cameras going once around ``center`` (one per frame for an orbit video)."""
    K = intrinsics(width, height_px, fov_y_deg)
    c = np.asarray(center, np.float64)
    cams = []
    for i in range(n):
        a = np.radians(start_deg + 360.0 * i / max(n, 1))
        eye = c + [radius * np.cos(a), radius * np.sin(a), 0.0]
        eye[2] = height
        cams.append(Camera(f"orbit{i:04d}", width, height_px, K, look_at(eye, c)))
    return cams


def render_sequence(seq, out: str | Path, *, cameras: list[Camera] | None = None, orbit: bool = True,
                    light: str = "studio", texture: np.ndarray | None = None, spp: int = 32,
                    width: int = 512, height: int = 512, progress=True, fps: float | None = None) -> dict:
    """Render every frame of ``seq`` (a stages.animate.Sequence) into ``out``/frames + video.mp4.

    With ``cameras``, frame t is seen from every camera (one subfolder each, one video each);
    otherwise from an orbiting camera (one per frame). ``light`` is a name of
    :func:`physavatar.render.lights.named_lights` (``fitted``: the avatar's light.json), aimed at
    the first frame. ``progress``: anything :func:`physavatar.progress.resolve` accepts.
    """
    from ..body.preview import write_video
    from ..capture import save_png
    from ..render import SceneSpec, linear_to_srgb8, load_scene, render
    from ..render.avatar import AvatarMeshes

    out = Path(out)
    V = seq.vertices
    center = light_center(V[0])
    lights = named_lights(light, center, fitted=Path(seq.avatar) / "light.json" if seq.avatar is not None else None)
    if texture is None and seq.avatar is not None:
        p = Path(seq.avatar) / "texture_linear.npy"
        texture = np.load(p).astype(np.float32) if p.exists() else None
    textured = texture is not None and seq.face_uvs is not None
    meshes = AvatarMeshes.build(V[0], seq.faces, seq.face_uvs if textured else None, seq.labels)
    if cameras is None:
        cameras_per_frame = [[c] for c in orbit_cameras(center, len(V), width=width, height_px=height)] if orbit \
            else [[orbit_cameras(center, 1, width=width, height_px=height)[0]]] * len(V)
        names = ["orbit"]
    else:
        cameras_per_frame = [cameras] * len(V)
        names = [c.name for c in cameras]
    frames = {n: [] for n in names}
    with resolve(progress).task("rendering", total=len(V)) as task:
        for t in range(len(V)):
            scene = load_scene(SceneSpec(meshes=meshes.specs(V[t], texture if textured else None), lights=lights))
            for name, cam in zip(names, cameras_per_frame[t]):
                img = linear_to_srgb8(render(scene, cam, spp=spp, seed=t).rgb)
                save_png(out / "frames" / name / f"{t:06d}.png", img)
                frames[name].append(img)
            task.advance()
    videos = []
    for name, imgs in frames.items():
        path = out / (f"{name}.mp4")
        write_video(path, imgs, fps or seq.fps)
        videos.append(str(path))
    write_json_atomic(out / "render.json", {"light": light, "spp": spp, "frames": int(len(V)), "views": names,
                                            "videos": videos, "textured": texture is not None})
    return {"videos": videos, "frames": int(len(V))}


def _csv(text: str) -> tuple[str, ...]:
    return tuple(c for c in text.split(",") if c)


@dataclass(frozen=True)
class RenderConfig:
    light: str = option("studio", "fitted, studio, ambient, sky, sun, point, or an .hdr/.exr environment map")
    cameras: tuple[str, ...] = option((), "with --capture: comma-separated camera names (default all)", parse=_csv)
    spp: int = option(32, "samples per pixel", check=lambda v: None if v >= 1 else "spp must be >= 1 and size >= 16",
                      flag="--spp")
    size: int = option(512, "orbit image size (pixels)",
                       check=lambda v: None if v >= 16 else "spp must be >= 1 and size >= 16")


def pipeline_config(light: str, quick: bool) -> RenderConfig:
    """What ``physavatar run`` renders: the held-out motion's orbit under ``light`` (fitted, and sky
    for the relit version); 16 spp at 128 px with ``quick``, else 32 spp at 512 px."""
    return RenderConfig(light=light, spp=16, size=128) if quick else RenderConfig(light=light, spp=32)


def run(sequence: Path, *, out: Path, config: RenderConfig, capture: Path | None = None, progress=None) -> dict:
    """Render the animate output ``sequence`` into ``out`` (frames/, one MP4 per view,
    render.json), from ``capture``'s cameras (``config.cameras`` of them, default all) or an orbit."""
    s = AnimatedSequence.load(sequence)
    cams = None
    if capture is not None:
        from ..capture import load_capture

        cams = load_capture(capture).cameras
        if config.cameras:
            unknown = [c for c in config.cameras if c not in {k.name for k in cams}]
            if unknown:
                raise PhysavatarError(None, f"option --cameras: unknown camera(s) {unknown}")
            cams = [c for c in cams if c.name in config.cameras]
    return render_sequence(s, out, cameras=cams, light=config.light, spp=config.spp, width=config.size,
                           height=config.size, progress=progress)
