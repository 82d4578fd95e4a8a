"""``physavatar import``: a dataset folder in another tool's format -> a capture folder."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ._common import app, console, err_console, handle_errors


@app.command("import")
@handle_errors
def import_(
    src: Path = typer.Argument(..., help="the dataset folder (or its calibration file)"),
    out: Path = typer.Argument(..., help="output capture folder (must not exist or be empty)"),
    format: Optional[str] = typer.Option(None, "--format", help="actorshq, 4d-dress, easymocap, pose2sim or nerfstudio "
                                                                "(default: guessed from SRC's files)"),
    frames: Optional[str] = typer.Option(None, help="source frame ids to keep, e.g. 0-99 or 0,10,20-30"),
    every: int = typer.Option(1, help="keep every n-th of the selected frames"),
    start: Optional[float] = typer.Option(None, help="first time kept, seconds from the first frame"),
    end: Optional[float] = typer.Option(None, help="last time kept, seconds from the first frame"),
    resolution: Optional[str] = typer.Option(None, help="a factor (0.5) or WxH in pixels (540x960)"),
    fps: Optional[float] = typer.Option(None, help="frame rate (default: the source's or its videos')"),
    truncate: bool = typer.Option(False, "--truncate", help="cut cameras with more frames to the frames all have "
                                                             "(default: differing frame counts are an error)"),
    up: str = typer.Option("auto", help="the source world's up axis: auto (from the cameras), x, y, z, -x, -y, -z"),
    scale: float = typer.Option(1.0, help="metres per source unit"),
    floor: str = typer.Option("auto", help="auto (first mesh's lowest point to z=0 when the source has meshes), "
                                            "keep, or the floor height to move to z=0"),
    videos: Optional[Path] = typer.Option(None, help="folder of videos to use (pose2sim, easymocap; default videos/)"),
    anny: Optional[Path] = typer.Option(None, help="Anny's own pose parameters (.npz) in the source's world: "
                                                    "converted to body.npz"),
):
    """Import a calibrated multi-view capture (ActorsHQ, 4D-DRESS, EasyMocap, Pose2Sim TOML, nerfstudio)."""
    from ..importers import ImportOptions, import_capture

    opts = ImportOptions(frames=frames, every=every, start=start, end=end, resolution=resolution, fps=fps,
                         truncate=truncate, up=up, scale=scale, floor=floor, videos=videos,
                         anny=anny)
    r = import_capture(src, out, format=format, options=opts, progress=True)
    for w in r.warnings:
        err_console.print(f"[yellow]warning:[/] {w}", highlight=False, soft_wrap=True)
    extra = "".join([", masks" if r.masks else "", f", {r.meshes} meshes" if r.meshes else "",
                     ", body poses (body.npz)" if r.body else "",
                     f", {r.body_files} body-parameter files" if r.body_files else ""])
    console.print(f"wrote capture {r.out} from {r.format}: {len(r.cameras)} cameras, {len(r.frames)} of "
                  f"{r.source_frames} frames at {r.fps:g} fps, up axis {r.up}{extra}", highlight=False)
