"""Commands on data: inspect, synth, render-capture, motion list / preview / import, pose."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

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

    problems = validate_capture(capture, deep=not quick)
    if not problems:  # the pieces together: cameras against masks, and the ground truth
        cap = load_capture(capture)
        problems = [CaptureError(p, m) for p, m in alignment_problems(cap) + ground_truth_problems(cap)]
    if problems:
        for p in problems:
            err_console.print(f"[bold red]error:[/] {p}", highlight=False, soft_wrap=True)
        err_console.print(f"{len(problems)} problem(s) in {capture}")
        raise typer.Exit(2)
    s = summarize(load_capture(capture))
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
    motion: str = typer.Argument(..., help="built-in name (see 'motion list'), or a .bvh / .npz file"),
    out: Path = typer.Option(..., "--out", "-o", help="output .mp4 or .gif"),
    fps: float = typer.Option(25.0, help="frames per second of the preview"),
    duration: float = typer.Option(4.0, help="seconds (built-in motions)"),
    max_frames: int = typer.Option(150, help="at most this many frames"),
    mapping: Optional[Path] = typer.Option(None, help="BVH joint-name mapping overrides (JSON)"),
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
    bvh: Path = typer.Argument(..., help="a .bvh file"),
    out: Path = typer.Option(..., "--out", "-o", help="output motion .npz"),
    fps: Optional[float] = typer.Option(None, help="resample to this fps (default: keep the file's)"),
    mapping: Optional[Path] = typer.Option(None, help="JSON of {bvh_joint: anny_bone} overrides"),
):
    """Import a BVH file (CMU, Mixamo-style) retargeted to Anny, as a motion .npz."""
    from ..body import BodyModel
    from ..body.bvh import import_bvh

    m = import_bvh(bvh, BodyModel(topology="collider"), mapping=mapping)
    if fps:
        m = m.resample(fps)
    m.save(out)
    console.print(f"wrote {out}: {m.frames} frames at {m.fps:g} fps, "
                  f"{len(m.meta['mapped_joints'])} joints mapped, {m.meta['scale_m_per_unit']:.4f} m per file unit")


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
