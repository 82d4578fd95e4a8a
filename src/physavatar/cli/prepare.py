"""``physavatar prepare CAPTURE OUT``: fill in what a capture lacks (options from PrepareConfig)."""

from __future__ import annotations

from pathlib import Path

import typer

from ..stages.prepare import PrepareConfig
from ._common import app, console, handle_errors
from .options import config_command


@config_command(app, "prepare", PrepareConfig, wrap=handle_errors)
def prepare(
    capture: Path = typer.Argument(..., help="capture folder (from `physavatar import` or a rig): capture.json, "
                                             "cameras.json, images/; masks, body.npz, meshes/ optional"),
    out: Path = typer.Argument(..., help="the prepared capture folder to write"),
    *,
    config: PrepareConfig,
):
    """Prepare a capture: masks, first-frame mesh, Anny body per frame, garment segmentation, boundary
    vertices, UVs and a report; each step is skipped when the capture gives its output (docs/prepare.md)."""
    from ..files import read_json
    from ..stages.prepare import run

    run(capture, out=out, config=config, progress=True)
    info = read_json(out / "prepare.json")
    for step, what in info["steps"].items():
        console.print(f"{step:13s} {what}")
    console.print(f"wrote {out} in {info['seconds'].get('total', 0):.0f} s"
                  + (f"; report: {out / 'prepare' / 'report.md'}" if config.report else ""))
