"""Commands on data: inspect, synth, render-capture, motion list / preview / import / inspect, pose."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.table import Table

from .options import config_command
from ..stages.pose import PoseConfig
from ._common import app, bad_option, console, err_console, handle_errors, motion_app


@app.command()
@handle_errors
def inspect(
    capture: Path = typer.Argument(..., help="capture folder"),
    quick: bool = typer.Option(False, "--quick", help="decode only the first frame's images (every file is still checked to exist)"),
    as_json: bool = typer.Option(False, "--json", help="print the summary as JSON"),
):
    """Summarize a capture folder, or list every validation problem (exit code 2)."""
    from ..capture import CaptureError, load_capture, summarize, validate_capture
    from ..capture_checks import alignment_problems
    from ..data.ground_truth import ground_truth_problems

    problems, cap = validate_capture(capture, deep=not quick), None
    if not problems:  # the pieces together: cameras against masks, and the ground truth
        cap = load_capture(capture)
        problems = [CaptureError(p, m) for p, m in alignment_problems(cap) + ground_truth_problems(cap)]
    if problems:
        for p in problems:
            err_console.print(f"[bold red]error:[/] {p}", highlight=False, soft_wrap=True)
        err_console.print(f"{len(problems)} problem(s) in {capture}")
        raise typer.Exit(2)
    s = summarize(cap)
    if as_json:
        console.print_json(json.dumps(s))
        return
    t = Table(title=f"capture {capture}", show_header=False)
    for k, v in s.items():
        if isinstance(v, dict):
            v = ", ".join(f"{a}={b:.2f}" for a, b in v.items())
        t.add_row(k.replace("_", " "), str(v))
    console.print(t)


@motion_app.command("list")
def motion_list():
    """List the built-in motions."""
    from ..body.motion import BUILTIN

    t = Table("name", "what")
    for name, (_, doc) in BUILTIN.items():
        t.add_row(name, doc)
    console.print(t)


@motion_app.command("preview")
@handle_errors
def motion_preview(
    motion: str = typer.Argument(..., help="built-in name (see 'motion list'), a .bvh file, or a motion or AMASS .npz"),
    out: Path = typer.Option(..., "--out", "-o", help="output .mp4 or .gif"),
    fps: float = typer.Option(25.0, help="frames per second of the preview"),
    duration: float = typer.Option(4.0, help="seconds (built-in motions)"),
    max_frames: int = typer.Option(150, help="at most this many frames"),
    mapping: Optional[Path] = typer.Option(None, help="JSON of {joint: anny_bone} overrides of the automatic joint map (.bvh, AMASS .npz)"),
):
    """Render a quick preview of a motion on the (decimated) Anny body, front and side."""
    from ..body import BodyModel
    from ..body.load import load_motion
    from ..body.preview import render_frames, write_video

    if out.suffix.lower() not in (".mp4", ".gif"):
        bad_option("--out", f"{out} must end in .mp4 or .gif")
    body = BodyModel(topology="collider")
    m = load_motion(motion, fps, duration, mapping=mapping, body=body)
    if m.frames > max_frames:
        m = m.slice(0, max_frames)
    posed = m.pose(body)
    frames = render_frames(posed.vertices, body.faces, posed.joints, body.parents, title=m.name, progress=True)
    write_video(out, frames, fps)
    console.print(f"wrote {out} ({m.frames} frames at {fps:g} fps)")


@motion_app.command("import")
@handle_errors
def motion_import(
    file: Path = typer.Argument(..., help="a .bvh file or an AMASS/SMPL .npz (poses, trans, mocap_framerate)"),
    out: Path = typer.Option(..., "--out", "-o", help="output motion .npz"),
    fps: Optional[float] = typer.Option(None, help="resample to this fps (default: keep the file's)"),
    mapping: Optional[Path] = typer.Option(None, help="JSON of {joint: anny_bone} overrides of the automatic joint map"),
):
    """Import motion capture (any BVH skeleton, AMASS/SMPL npz) retargeted to Anny, as a motion .npz."""
    from ..body import BodyModel
    from ..body.load import inspect_capture

    m = inspect_capture(file, BodyModel(topology="collider"), mapping)["motion"]
    if fps:
        m = m.resample(fps)
    m.save(out)
    console.print(f"wrote {out}: {m.frames} frames at {m.fps:g} fps, "
                  f"{len(m.meta['mapped_joints'])} joints mapped, {m.meta['scale_m_per_unit']:.4f} m per file unit "
                  f"('physavatar motion inspect {file}' shows the joint map and why)")


def _axis_name(v) -> str:
    v = np.asarray(v, float)
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) > 0.985:
        return ("+" if v[k] > 0 else "-") + "xyz"[k]
    return "(" + ", ".join(f"{x:+.2f}" for x in v) + ")"


@motion_app.command("inspect")
@handle_errors
def motion_inspect(
    file: Path = typer.Argument(..., help="a .bvh file or an AMASS/SMPL .npz"),
    mapping: Optional[Path] = typer.Option(None, help="JSON of {joint: anny_bone} overrides of the automatic joint map"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="preview: .png (frames side by side) or .gif/.mp4 "
                                       "(default: FILE-preview.png in the current folder)"),
    preview: bool = typer.Option(True, "--preview/--no-preview", help="write the preview"),
    frames: int = typer.Option(4, help="frames in a .png preview (evenly spread over the clip)"),
    max_frames: int = typer.Option(150, help="at most this many frames in a .gif/.mp4 preview (at 25 fps)"),
):
    """Show a motion file's skeleton, the joint map onto Anny and why each joint was chosen, the
    axes and scale found, and write a preview of the retargeted motion."""
    from ..body import BodyModel
    from ..body.load import inspect_capture

    out = out or Path(f"{file.stem}-preview.png")
    if preview and out.suffix.lower() not in (".png", ".gif", ".mp4"):
        bad_option("--out", f"{out} must end in .png, .gif or .mp4")
    body = BodyModel(topology="collider")
    info = inspect_capture(file, body, mapping)
    m = info["motion"]
    names, parents, ch = info["names"], info["parents"], info["channels"]
    console.print(f"[bold]{file}[/]: {info['kind']}, {len(names)} joints, {info['frames']} frames at {info['fps']:g} fps")
    lines = []

    def tree(j, depth):
        lines.append("  " * depth + names[j] + (f"  ({ch[j]} channels)" if ch else ""))
        for k in [k for k in range(len(names)) if parents[k] == j]:
            tree(k, depth + 1)

    for r in [j for j in range(len(names)) if parents[j] < 0]:
        tree(r, 0)
    console.print("skeleton:\n" + "\n".join(lines), highlight=False)
    t = Table("joint", "Anny bone", "why", title="joint map")
    mapped, why = m.meta["mapped_joints"], m.meta["mapping_why"]
    for n in names:
        t.add_row(n, mapped.get(n, "-"), why.get(n, ""))
    console.print(t)
    C = np.asarray(m.meta["axes"])
    console.print(f"axes (from {m.meta['calibration']}): the file's up is {_axis_name(C[2])}, its left "
                  f"{_axis_name(C[0])}, its forward {_axis_name(-C[1])} (Anny: up +z, left +x, forward -y)")
    console.print(f"scale: {m.meta['scale_m_per_unit']:.5g} m per file unit (Anny's leg length over the file's)")
    if not preview:
        return
    from ..body.preview import render_frames, write_video

    if out.suffix.lower() == ".png":
        from ..capture import save_png

        idx = np.unique(np.linspace(0, m.frames - 1, max(1, frames)).round().astype(int))
        sub = _frames(m, idx)
        posed = sub.pose(body)
        imgs = render_frames(posed.vertices, body.faces, posed.joints, body.parents,
                             title=f"{m.name} (of frames {', '.join(map(str, idx))}):")
        save_png(out, np.concatenate(imgs, axis=0))
    else:
        mm = m.resample(25.0)
        mm = mm.slice(0, min(mm.frames, max_frames))
        posed = mm.pose(body)
        imgs = render_frames(posed.vertices, body.faces, posed.joints, body.parents, title=m.name, progress=True)
        write_video(out, imgs, 25.0)
    console.print(f"wrote {out}")


def _frames(m, idx):
    """The frames ``idx`` of motion ``m``."""
    from ..body.motion import Motion

    return Motion(m.name, m.fps, m.bone_names, m.rotations[idx], m.root_translation[idx], dict(m.meta))


@app.command()
@handle_errors
def synth(
    out: Path = typer.Argument(..., help="output capture folder (must not exist or be empty)"),
    preset: str = typer.Option("demo", help="tiny (for tests, seconds) or demo (the standard case)"),
    garment: Optional[str] = typer.Option(None, help="dress, skirt or tshirt (overrides the preset)"),
    motion: Optional[str] = typer.Option(None, help="built-in motion of the capture (overrides the preset)"),
    frames: Optional[int] = typer.Option(None, help="number of frames (overrides the preset)"),
    seed: Optional[int] = typer.Option(None),
):
    """Render a synthetic capture with ground truth (body + garment, textures, soft shadows)."""
    from ..synth import preset_config, synthesize

    cfg = preset_config(preset, garment=garment, motion=motion, frames=frames, seed=seed)
    t0 = time.time()
    path = synthesize(out, cfg)
    console.print(f"wrote capture {path} in {time.time() - t0:.0f} s "
                  f"({cfg.n_ring + cfg.n_elevated} cameras {cfg.width}x{cfg.height}, {cfg.frames} frames, "
                  f"garment {cfg.garment!r}, motion {cfg.motion!r}; held-out motion {cfg.heldout_motion!r})")


@app.command("render-capture")
@handle_errors
def render_capture(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="contact sheet PNG"),
    frame: Optional[int] = typer.Option(None, help="frame id (default: the first)"),
):
    """Write a contact sheet: all cameras of one frame in one labelled PNG."""
    from ..capture import save_png
    from ..synth import contact_sheet_for

    if out.suffix.lower() != ".png":
        bad_option("--out", f"{out} must end in .png")
    sheet = contact_sheet_for(capture, frame)
    save_png(out, sheet)
    console.print(f"wrote {out} ({sheet.shape[1]}x{sheet.shape[0]})")


@config_command(app, "pose", PoseConfig, wrap=handle_errors)
def pose(out: Path = typer.Option(..., "--out", "-o", help="output folder"), *, config: PoseConfig):
    """Build an Anny body, pose it with a motion, write the mesh sequence (npz + PLY per frame)."""
    from ..stages.pose import run

    r = run(out=out, config=config, progress=True)
    console.print(f"posed Anny ({config.topology}: {r.vertices} vertices, {r.bones} bones; "
                  f"loaded in {r.load_seconds:.1f} s) with motion {r.motion!r}: {r.frames} frames at {config.fps:g} fps")
    console.print("wrote " + ", ".join(r.files))
