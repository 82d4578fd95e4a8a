"""``physavatar batch``: ``run`` for many captures, on this machine or on Ray (physavatar.batch)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..pipeline import RunConfig
from ._common import app, console, handle_errors
from .options import config_command


@config_command(app, "batch", RunConfig, wrap=handle_errors)
def batch(captures: List[str] = typer.Argument(..., help="capture folders, glob patterns (quoted) or .txt lists "
                                                          "(one folder or pattern a line)"),
          out: Path = typer.Option(..., "--out", help="output folder: OUT/<name>/ per capture, OUT/batch.md"),
          jobs: Optional[int] = typer.Option(None, "--jobs", min=1, help="captures side by side on this machine "
                                             "(default: one per core, PHYSAVATAR_WORKERS split between them)"),
          ray: bool = typer.Option(False, "--ray", help="run every stage as a Ray task, on an embedded local Ray "
                                   "(or the cluster in $RAY_ADDRESS). Needs: pip install 'physavatar\\[ray]'"),
          ray_address: Optional[str] = typer.Option(None, "--ray-address", metavar="ADDRESS",
                                                    help="like --ray, on the Ray cluster at ADDRESS (auto, "
                                                         "ray://head:10001); OUT must be on storage all nodes see"),
          ray_cpus: Optional[int] = typer.Option(None, "--ray-cpus", min=1, help="CPUs of the embedded local Ray "
                                                 "(default: all)"),
          *, config: RunConfig):
    """Run the whole pipeline for every capture into OUT/<name>/ (same options and resume rules as
    `run`); a failed capture is reported and the others go on; writes OUT/batch.json and
    OUT/batch.md (a table linking each run's report)."""
    from ..batch import run_batch, table

    b = run_batch(captures, out, config, jobs=jobs, ray=ray_address or ("local" if ray else None), ray_cpus=ray_cpus,
                  say=lambda text: console.print(text, highlight=False))
    from rich.markup import escape
    from rich import box
    from rich.table import Table

    head, rows = table(b, stages=["track", "physics", "appearance"])  # the long stages; all of them in batch.md
    short = {"stages s": "total s", "track s": "track", "physics s": "physics", "appearance s": "appear.",
             "chamfer ×1e3": "chamfer", "track mm": "trk mm"}
    keep = [i for i, h in enumerate(head) if h != "stretch N/m"]
    t = Table(title=f"physavatar batch: {b['ok']} ok, {b['failed']} failed, {b['seconds']:.0f} s (seconds per "
                    "stage; chamfer ×1e3, tracking error mm)", box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    for i in keep:
        t.add_column(short.get(head[i], head[i]), justify="left" if i < 2 else "right", no_wrap=True)
    for row in rows:
        t.add_row(*(escape(row[i]) for i in keep), style=None if row[1] == "ok" else "red")
    console.print(t)
    for r in b["captures"]:
        if r["status"] != "ok":
            console.print(f"[red]{escape(r['name'])}[/]: {escape(str(r['error']))}", highlight=False, soft_wrap=True)
    console.print(f"wrote {out / 'batch.md'}, {out / 'batch.json'}")
    if b["failed"]:
        raise typer.Exit(1)
