"""Rendering an animated avatar sequence: PNG frames and an MP4, from capture cameras or an orbit,
under the fitted light or any new one (relighting, paper Sec. 3.3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera, intrinsics, look_at
from ..errors import PhysavatarError
from ..files import write_json_atomic

LIGHTS = ("fitted", "studio", "ambient", "sky", "sun")


def make_lights(spec: str, center, avatar_dir: Path | None):
    """Lights by name: ``fitted`` (the avatar's light.json), ``studio`` (ambient + soft key),
    ``ambient``, ``sky`` (a generated HDR sky), ``sun``, or an .hdr/.exr environment map file."""
    from ..render import Ambient, EnvMap, SunLight, sky_envmap, soft_studio

    c = tuple(float(x) for x in center)
    if spec == "fitted":
        if avatar_dir is None or not (Path(avatar_dir) / "light.json").exists():
            raise PhysavatarError(avatar_dir, "has no light.json (run fit-appearance, or choose another --light)")
        from .appearance import load_lights

        return load_lights(Path(avatar_dir) / "light.json")
    if spec == "studio":
        return soft_studio(target=c)
    if spec == "ambient":
        return [Ambient(1.0)]
    if spec == "sky":
        return [EnvMap(sky_envmap(), scale=1.0)]
    if spec == "sun":
        return [Ambient(0.25), SunLight(to_sun=(0.4, -0.6, 0.7), irradiance=3.0)]
    p = Path(spec)
    if p.suffix.lower() in (".hdr", ".exr"):
        if not p.is_file():
            raise PhysavatarError(p, "environment map not found")
        return [EnvMap(str(p))]
    raise PhysavatarError(None, f"unknown light {spec!r}: choose {', '.join(LIGHTS)} or an .hdr file")


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
                    width: int = 512, height: int = 512, progress: bool = True, fps: float | None = None) -> dict:
    """Render every frame of ``seq`` (a stages.animate.Sequence) into ``out``/frames + video.mp4.

    With ``cameras``, frame t is seen from every camera (one subfolder each, one video each);
    otherwise from an orbiting camera (one per frame).
    """
    from rich.progress import Progress

    from ..body.preview import write_video
    from ..capture import save_png
    from ..render import SceneSpec, linear_to_srgb8, load_scene, render
    from ..render.avatar import avatar_specs

    out = Path(out)
    V = seq.vertices
    center = V[0].mean(0)
    center[2] = 0.5 * (V[0, :, 2].max() + V[0, :, 2].min())
    lights = make_lights(light, center, seq.avatar)
    if texture is None and seq.avatar is not None:
        p = Path(seq.avatar) / "texture_linear.npy"
        texture = np.load(p).astype(np.float32) if p.exists() else None
    if cameras is None:
        cameras_per_frame = [[c] for c in orbit_cameras(center, len(V), width=width, height_px=height)] if orbit \
            else [[orbit_cameras(center, 1, width=width, height_px=height)[0]]] * len(V)
        names = ["orbit"]
    else:
        cameras_per_frame = [cameras] * len(V)
        names = [c.name for c in cameras]
    frames = {n: [] for n in names}
    with Progress(disable=not progress) as bar:
        task = bar.add_task("rendering", total=len(V))
        for t in range(len(V)):
            scene = load_scene(SceneSpec(meshes=avatar_specs(V[t], seq.faces, seq.labels, seq.face_uvs, texture),
                                         lights=lights))
            for name, cam in zip(names, cameras_per_frame[t]):
                img = linear_to_srgb8(render(scene, cam, spp=spp, seed=t).rgb)
                save_png(out / "frames" / name / f"{t:06d}.png", img)
                frames[name].append(img)
            bar.advance(task)
    videos = []
    for name, imgs in frames.items():
        path = out / (f"{name}.mp4")
        write_video(path, imgs, fps or seq.fps)
        videos.append(str(path))
    write_json_atomic(out / "render.json", {"light": light, "spp": spp, "frames": int(len(V)), "views": names,
                                            "videos": videos, "textured": texture is not None})
    return {"videos": videos, "frames": int(len(V))}
