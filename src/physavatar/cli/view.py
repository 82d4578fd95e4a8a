"""``physavatar view PATH``: the web viewer (``physavatar.viewer``)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ._common import app, console, handle_errors


@app.command()
@handle_errors
def view(
    path: Path = typer.Argument(..., help="a capture, a run folder, a track / simulate / animate output, an avatar, "
                                          "or a sequence .npz"),
    port: Optional[int] = typer.Option(None, help="port on 127.0.0.1 (default: a free one)"),
    save: Optional[Path] = typer.Option(None, help="write a self-contained HTML file that plays the scene without "
                                                   "the server, then exit"),
    max_frames: int = typer.Option(300, help="with --save: the most frames written"),
):
    """Look at a folder in the browser: meshes over time, cameras with their images, error against
    ground truth, material and metrics (docs/viewer.md)."""
    from ..viewer import Viewer, load_scene

    scene = load_scene(path)
    with Viewer(scene, port=port) as v:
        if save is not None:
            out = v.save_html(save, max_frames=max_frames)
            console.print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB; open it in a browser, no server needed)")
            return
        console.print(f"viewing {scene.kind} {scene.path}: {len(scene.layers)} layers, {scene.n_frames} frames, "
                      f"{len(scene.cameras)} cameras")
        for note in scene.notes:
            console.print(f"  note: {note}", highlight=False)
        console.print(f"open [bold]{v.url}[/] in a browser (Ctrl-C stops)")
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            console.print("viewer stopped")
