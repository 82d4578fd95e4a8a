"""Commands of the appearance stage: fit-appearance, relight (paper Sec. 3.3)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ..errors import PhysavatarError
from ._common import app, bad_option, console, handle_errors

@app.command("fit-appearance")
@handle_errors
def fit_appearance_cmd(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (a rerun with the same config resumes)"),
    tracked: Optional[Path] = typer.Option(None, "--tracked", help="tracking output folder (tracked.npz: meshes + Gaussian colours)"),
    meshes: str = typer.Option("tracked", "--meshes", help="tracked, or gt (ground_truth/meshes.npz of a synthetic capture)"),
    light: str = typer.Option("ambient", "--light", help="ambient (the paper: texture + L_a) or studio (+ the known key light's intensity)"),
    lighting: Optional[Path] = typer.Option(None, "--lighting", help="studio lights file (default ground_truth/lighting.json)"),
    iterations: int = typer.Option(2000, "--iterations", help="Adam steps (paper: 2000)"),
    texture_size: int = typer.Option(512, "--texture-size", help="atlas resolution in texels"),
    scale: float = typer.Option(1.0, "--scale", help="image resolution factor in (0, 1]"),
    spp: int = typer.Option(8, "--spp", help="samples per pixel while fitting (paper: 8)"),
    final_spp: int = typer.Option(128, "--final-spp", help="samples per pixel of the preview renders"),
    batch: int = typer.Option(1, "--batch", help="random (frame, camera) views per step"),
    lr: float = typer.Option(0.01, "--lr", help="Adam learning rate, halved every --decay-every steps"),
    decay_every: int = typer.Option(500, "--decay-every"),
    frame_stride: int = typer.Option(1, "--frame-stride", help="fit every k-th frame"),
    cameras: Optional[str] = typer.Option(None, "--cameras", help="training cameras CAM,CAM (default: all)"),
    fix_light: bool = typer.Option(False, "--fix-light", help="keep the light at its initial value"),
    seed: int = typer.Option(0, "--seed"),
    quick: bool = typer.Option(False, "--quick", help="a few-minute CPU budget: 200 iterations (lr 0.02) on half-resolution images, 32-spp previews"),
):
    """Fit a relightable diffuse texture and the light by inverse rendering (docs/appearance.md)."""
    import numpy as np

    from ..stages.appearance import AppearanceConfig, fit_appearance

    if meshes not in ("tracked", "gt"):
        bad_option("--meshes", f"{meshes!r} is not tracked or gt")
    if meshes == "tracked" and tracked is None:
        bad_option("--tracked", "needed with --meshes tracked (or pass --meshes gt for a synthetic capture)")
    cams = tuple(c.strip() for c in cameras.split(",") if c.strip()) if cameras else None
    cfg = AppearanceConfig(light=light, iterations=iterations, texture_size=texture_size, scale=scale, spp=spp,
                           final_spp=final_spp, batch=batch, lr=lr, lr_decay_every=decay_every,
                           frame_stride=frame_stride, cameras=cams, fit_light=not fix_light, seed=seed)
    if quick:
        from dataclasses import replace as _replace

        cfg = _replace(cfg, iterations=min(iterations, 200), scale=min(scale, 0.5), final_spp=min(final_spp, 32),
                       lr=max(lr, 0.02), lr_decay_every=min(decay_every, 50), init_frame_stride=4)
    t0 = time.time()
    res = fit_appearance(capture, out, cfg, tracked=tracked, meshes=meshes, lighting=lighting)
    amb = next((l.radiance for l in res.lights if type(l).__name__ == "Ambient"), None)
    losses = [r["loss"] for r in res.log]
    k = max(1, min(50, len(losses) // 4))
    msg = (f"fitted {cfg.texture_size}² texture + {cfg.light} light in {time.time() - t0:.0f} s "
           f"({res.seconds_per_iteration:.2f} s/iteration)")
    if losses:
        msg += f"; loss {np.mean(losses[:k]):.3g} -> {np.mean(losses[-k:]):.3g} (mean of {k} steps)"
    if amb is not None:
        msg += f"; ambient {tuple(round(float(a), 3) for a in np.broadcast_to(amb, 3))}"
    console.print(msg)
    console.print(f"wrote {out}/texture.png, texture_linear.npy, light.json, fit_log.csv, loss.png, preview.png")


@app.command()
@handle_errors
def relight(
    source: Path = typer.Argument(..., help="capture folder (ground-truth mesh) or tracking folder (tracked.npz)"),
    texture: Path = typer.Option(..., "--texture", help="fit-appearance output folder"),
    light: str = typer.Option("sky", "--light", help="fitted, studio, ambient, sky, sun, point, or an .hdr/.exr "
                              "environment map (docs/rendering.md)"),
    frame: Optional[int] = typer.Option(None, "--frame", help="frame id (default: the first)"),
    out: Path = typer.Option(..., "--out", "-o", help="contact sheet PNG"),
    capture: Optional[Path] = typer.Option(None, "--capture", help="capture folder for the cameras (when SOURCE is a tracking folder)"),
    spp: int = typer.Option(128, "--spp"),
    strength: float = typer.Option(1.0, "--strength", help="environment map scale"),
    scale: float = typer.Option(1.0, "--scale", help="image resolution factor"),
):
    """Render the avatar with its fitted texture under a new light, from every capture camera."""
    from ..capture import load_capture, save_png
    from ..data.tracked import FILE as TRACKED, TrackedSequence
    from ..files import load_npz, read_json
    from ..render import contact_sheet
    from ..render.lights import light_center, named_lights
    from ..stages.appearance import FittedAppearance, relight as run_relight

    if out.suffix.lower() != ".png":
        bad_option("--out", f"{out} must end in .png")
    if spp < 1 or not (0 < scale <= 1):
        bad_option("--spp/--scale", "spp >= 1 and scale in (0, 1]")
    fit = FittedAppearance.load(texture)
    if (source / TRACKED).is_file():
        tr = TrackedSequence.load(source, require=("vertices", "frames"))
        V_all, frames = tr.vertices, [int(f) for f in tr.frames]
        if capture is None:
            cfg_path = source / "config.json"
            guess = read_json(cfg_path).get("capture") if cfg_path.is_file() else None
            if not guess:
                bad_option("--capture", "needed to find the cameras of a tracking folder")
            capture = Path(guess)
        cap = load_capture(capture)
    else:
        cap = load_capture(source)
        if cap.ground_truth is None or not (cap.ground_truth / "meshes.npz").is_file():
            raise PhysavatarError(source, "no ground_truth/meshes.npz: pass a tracking folder instead")
        V_all, frames = load_npz(cap.ground_truth / "meshes.npz")["vertices"], list(cap.frames)
    f = frames[0] if frame is None else frame
    if f not in frames:
        bad_option("--frame", f"{f} is not one of the frames {frames[0]}..{frames[-1]}")
    V = V_all[frames.index(f)]
    t = cap.template
    if fit.face_uvs.shape != (len(t.faces), 3, 2):
        raise PhysavatarError(texture / "atlas.npz", "the atlas does not match this capture's template")
    lights = named_lights(light, light_center(V), fitted=fit.lights, strength=strength)
    imgs = []
    for cam in cap.cameras:
        r = run_relight(V, t.faces, fit.face_uvs, fit.texture, cam.scaled(scale), lights, labels=t.labels, spp=spp)
        imgs.append(r.srgb8())
    sheet = contact_sheet(imgs, [f"{c.name} {light if len(light) < 20 else Path(light).name}" for c in cap.cameras])
    save_png(out, sheet)
    console.print(f"wrote {out} ({len(imgs)} views of frame {f}, {sheet.shape[1]}x{sheet.shape[0]})")
