"""Commands of the appearance stage: fit-appearance, relight (paper Sec. 3.3)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ..stages import appearance
from ..stages import relight as relight_stage
from ..stages.appearance import AppearanceConfig
from ..stages.relight import RelightConfig
from ._common import app, console, handle_errors
from .options import config_command


@config_command(app, "fit-appearance", AppearanceConfig, wrap=handle_errors)
def fit_appearance_cmd(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder (a rerun with the same config resumes)"),
    tracked: Optional[Path] = typer.Option(None, "--tracked", help="tracking output folder (tracked.npz: meshes + Gaussian colours)"),
    lighting: Optional[Path] = typer.Option(None, "--lighting", help="studio lights file (default ground_truth/lighting.json)"),
    quick: bool = typer.Option(False, "--quick", help="a few-minute CPU budget: 200 iterations (lr at most 0.005) on half-resolution images, 32-spp previews"),
    *,
    config: AppearanceConfig,
):
    """Fit a relightable diffuse texture and the light by inverse rendering (docs/appearance.md)."""
    import numpy as np

    if quick:
        config = appearance.quick_preset(config)
    t0 = time.time()
    res = appearance.run(capture, out=out, config=config, tracked=tracked, lighting=lighting, progress=True)
    amb = next((l.radiance for l in res.lights if type(l).__name__ == "Ambient"), None)
    losses = [r["loss"] for r in res.log]
    k = max(1, min(50, len(losses) // 4))
    msg = (f"fitted {config.texture_size}² texture + {config.light} light in {time.time() - t0:.0f} s "
           f"({res.seconds_per_iteration:.2f} s/iteration)")
    if losses:
        msg += f"; loss {np.mean(losses[:k]):.3g} -> {np.mean(losses[-k:]):.3g} (mean of {k} steps)"
    if amb is not None:
        msg += f"; ambient {tuple(round(float(a), 3) for a in np.broadcast_to(amb, 3))}"
    console.print(msg)
    console.print(f"wrote {out}/texture.png, texture_linear.npy, light.json, fit_log.csv, loss.png, preview.png")


@config_command(app, "relight", RelightConfig, wrap=handle_errors)
def relight(
    source: Path = typer.Argument(..., help="capture folder (ground-truth mesh) or tracking folder (tracked.npz)"),
    texture: Path = typer.Option(..., "--texture", help="fit-appearance output folder"),
    out: Path = typer.Option(..., "--out", "-o", help="contact sheet PNG"),
    capture: Optional[Path] = typer.Option(None, "--capture", help="capture folder for the cameras (when SOURCE is a tracking folder)"),
    *,
    config: RelightConfig,
):
    """Render the avatar with its fitted texture under a new light, from every capture camera."""
    res = relight_stage.run(source, out=out, config=config, texture=texture, capture=capture, progress=True)
    console.print(f"wrote {res.out} ({res.views} views of frame {res.frame}, {res.size[0]}x{res.size[1]})")
