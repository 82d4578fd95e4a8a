"""The tracking command (paper Sec. 3.1): options from :class:`TrackConfig`, then the stage."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from ..stages.base import set_path
from ..stages.track.config import TrackConfig
from ._common import app, console, handle_errors
from .options import config_command


@config_command(app, "track", TrackConfig, wrap=handle_errors)
def track(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (a rerun with the same config and capture data resumes)"),
    no_iso: bool = typer.Option(False, "--no-iso", help="drop the isometry loss (ablation)"),
    no_normal: bool = typer.Option(False, "--no-normal", help="drop the normal loss (ablation)"),
    material: Path = typer.Option(None, "--material", help="fit-physics output (folder or material.json) for the "
                                  "physics prediction: a second pass, as `run --track-passes 2` makes it "
                                  "(docs/tracking.md)"),
    *,
    config: TrackConfig,
):
    """Track the template through the capture with mesh-aligned Gaussians (docs/tracking.md)."""
    from ..stages.track import run

    if no_iso:
        config = set_path(config, "loss.iso_weight", 0.0)
    if no_normal:
        config = set_path(config, "loss.normal_weight", 0.0)
    t0 = time.time()
    res = run(capture, out=out, config=config, progress=True, material=material)
    console.print(f"tracked {len(res.frames)} frames ({len(res.computed)} fitted now, the rest resumed) "
                  f"in {time.time() - t0:.0f} s; wrote {out}/tracked.npz, frames/, meshes/, track_log.csv")
