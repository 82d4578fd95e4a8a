"""The tracking command (paper Sec. 3.1)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ._common import app, bad_option, console, handle_errors

@app.command()
@handle_errors
def track(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (a rerun with the same config resumes)"),
    frames: Optional[int] = typer.Option(None, "--frames", help="track only the first N frames"),
    holdout: Optional[str] = typer.Option(None, "--holdout", help="cameras excluded from fitting, CAM,CAM ('' for none; default: two)"),
    iters_first: Optional[int] = typer.Option(None, "--iters-first", help="max iterations per pyramid level, frame 1"),
    iters: Optional[int] = typer.Option(None, "--iters", help="max iterations per pyramid level, later frames"),
    scale: Optional[float] = typer.Option(None, "--scale", help="resolution factor of the finest level, in (0, 1]"),
    no_iso: bool = typer.Option(False, "--no-iso", help="drop the isometry loss (ablation)"),
    no_normal: bool = typer.Option(False, "--no-normal", help="drop the normal loss (ablation)"),
    init: Optional[str] = typer.Option(None, "--init", help="start of each frame: mixed (body and garment boundary skinned from body.npz, the rest of the garment "
                                        "by constant velocity; default), lbs (all skinned + carried residual) or velocity"),
    garment_start: Optional[str] = typer.Option(None, "--garment-start", help="start of the free garment under --init mixed: "
                                                 "flow (multi-view optical flow + model-based corrections; default), velocity or physics"),
):
    """Track the template through the capture with mesh-aligned Gaussians (docs/tracking.md)."""
    from dataclasses import replace as _replace

    from ..stages.track import TrackConfig, track as run_track

    cfg = TrackConfig()
    changes = {}
    if frames is not None:
        changes["n_frames"] = frames
    if holdout is not None:
        changes["holdout"] = tuple(h.strip() for h in holdout.split(",") if h.strip())
    if init is not None and init not in ("mixed", "lbs", "velocity"):
        bad_option("--init", f"{init!r} is not mixed, lbs or velocity")
    if garment_start is not None:
        if garment_start not in ("flow", "velocity", "physics"):
            bad_option("--garment-start", f"{garment_start!r} is not flow, velocity or physics")
        changes["garment_prediction"] = garment_start
    for name, value in (("iters_first", iters_first), ("iters", iters), ("scale", scale), ("init", init)):
        if value is not None:
            changes[name] = value
    if no_iso:
        changes["iso_weight"] = 0.0
    if no_normal:
        changes["normal_weight"] = 0.0
    cfg = _replace(cfg, **changes)
    t0 = time.time()
    res = run_track(capture, out, cfg)
    console.print(f"tracked {len(res.frames)} frames ({len(res.computed)} fitted now, the rest resumed) "
                  f"in {time.time() - t0:.0f} s; wrote {out}/tracked.npz, frames/, meshes/, track_log.csv")
