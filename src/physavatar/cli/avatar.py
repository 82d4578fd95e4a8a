"""Commands on avatars and runs: build-avatar, animate, render, export, evaluate, reference-sims, run."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..pipeline import RunConfig
from ..stages.animate import AnimateConfig
from ..stages.evaluate import EvaluateConfig, ReferencesConfig
from ..stages.export import ExportConfig
from ..stages.render import RenderConfig
from ._common import app, console, handle_errors, say_clearance
from .options import config_command


@app.command("build-avatar")
@handle_errors
def build_avatar_cmd(
    capture: Path = typer.Argument(..., help="capture folder"),
    out: Path = typer.Option(..., "--out", "-o", help="avatar folder"),
    material: str = typer.Option(..., help="material.json (fit-physics output) or a preset: silk, cotton, denim"),
    appearance: Optional[Path] = typer.Option(None, help="fit-appearance output folder (texture, light)"),
    tracked: Optional[Path] = typer.Option(None, help="tracking output folder: use the tracked frame 1 as the template"),
):
    """Bundle template, transferred skinning weights, material, texture and light into an avatar folder."""
    from ..stages.avatar import run

    av = run(capture, out=out, material=material, appearance=appearance, tracked=tracked)
    console.print(f"wrote avatar {out}: {len(av.template.vertices)} vertices "
                  f"({int(av.template.garment_mask.sum())} garment), material {av.material.name or 'fitted'}, "
                  f"texture {'yes' if av.texture is not None else 'no'}, "
                  f"skinning matched {av.meta['skinning_matched_fraction']:.0%} (rest inpainted)")


@config_command(app, "animate", AnimateConfig, wrap=handle_errors)
def animate(avatar: Path = typer.Argument(..., help="avatar folder (build-avatar)"),
            out: Path = typer.Option(..., "--out", "-o", help="sequence folder"), *, config: AnimateConfig):
    """Drive the avatar with a new motion: body by skinning, garment simulated with its material."""
    from ..stages.animate import run

    r = run(avatar, out=out, config=config, progress=True)
    say_clearance(r.clearance, config.arm_clearance, r.part_clearance)
    st = r.stats
    console.print(f"animated {st['frames']} frames (+{st['warmup_frames']} warm-up) at {st['sim_fps']:.2f} "
                  f"simulated frames/s; wrote {out}/sequence.npz, meshes/")


@config_command(app, "render", RenderConfig, wrap=handle_errors)
def render(seq: Path = typer.Argument(..., help="sequence folder (animate)"),
           out: Path = typer.Option(..., "--out", "-o", help="output folder (frames/ and MP4)"),
           capture: Optional[Path] = typer.Option(None, help="render from this capture's cameras instead of an orbit"),
           *, config: RenderConfig):
    """Render a sequence to PNG frames and MP4 under the fitted or a new light."""
    from ..stages.render import run

    r = run(seq, out=out, config=config, capture=capture, progress=True)
    console.print(f"rendered {r['frames']} frames; wrote {', '.join(r['videos'])}")


@config_command(app, "export", ExportConfig, wrap=handle_errors)
def export(seq: Path = typer.Argument(..., help="sequence folder (animate)"),
           out: Path = typer.Option(..., "--out", "-o", help="output file (.usd/.usdc/.usda/.glb) or folder (obj, ply)"),
           *, config: ExportConfig):
    """Export a sequence: USD (time-sampled points, UVs, textured material), glTF binary, OBJ/PLY sequences."""
    from ..data.animated import AnimatedSequence
    from ..stages.export import run

    path = run(seq, out=out, config=config)
    frames = len(AnimatedSequence.load(seq).vertices)
    console.print(f"exported {frames} frames as {config.format or path.suffix.lstrip('.')}: {path}")


@config_command(app, "evaluate", EvaluateConfig, wrap=handle_errors)
def evaluate(
    capture: Path = typer.Argument(..., help="capture (a synthetic one's ground_truth/ adds the geometry rows)"),
    avatar: Path = typer.Option(..., help="avatar folder (build-avatar)"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder: metrics.json, report.md, views/"),
    tracked: Optional[Path] = typer.Option(None, help="tracking output: score its held-out cameras; with ground truth, also tracking error"),
    sequence: Optional[Path] = typer.Option(None, help="animate output on the held-out motion: reuse it as the estimated-material row"),
    references: Optional[Path] = typer.Option(None, help="reference-sims output of this capture: reuse its true- and random-material rows"),
    oracle: Optional[Path] = typer.Option(None, help="fit-physics output fitted on the capture's true meshes: one more row"),
    *, config: EvaluateConfig,
):
    """Metrics: PSNR/SSIM/LPIPS on the capture's held-out cameras (any capture, with --tracked); with
    ground truth, garment/full Chamfer and F-scores on the held-out motion for LBS, random,
    estimated and true material, its held-out views, and tracking error."""
    from ..stages.evaluate import run

    run(capture, out=out, config=config, avatar=avatar, tracked=tracked, sequence=sequence, references=references,
        oracle=oracle, progress=True)
    console.print((out / "report.md").read_text())


@config_command(app, "reference-sims", ReferencesConfig, wrap=handle_errors)
def reference_sims(capture: Path = typer.Argument(..., help="synthetic capture (with ground_truth/)"),
                   out: Path = typer.Option(..., "--out", "-o", help="output folder: avatar/, true/, random-<seed>/, references.json"),
                   *, config: ReferencesConfig):
    """The evaluation's reference rows ahead of time: the garment on the held-out motion with the
    true and with the random material (they need nothing fitted; `run` makes them while tracking)."""
    from ..stages.evaluate import run_references

    from ..files import read_json

    run_references(capture, out=out, config=config, progress=True)
    refs = read_json(out / "references.json")
    console.print(f"wrote {', '.join(f'{out}/{d} ({r})' for r, d in zip(refs['rows'], refs['folders']))}")
    console.print(f"random draws simulated with contact offset {1e3 * refs['contact_offset_m']:.2f} mm "
                  f"({refs['contact_offset'].get('method')})")


@config_command(app, "run", RunConfig, wrap=handle_errors)
def run(capture: Path = typer.Argument(..., help="capture folder"),
        out: Path = typer.Argument(..., help="output folder (resumes when it exists)"), *, config: RunConfig):
    """Run the whole pipeline: track, fit-physics, fit-appearance, build-avatar, animate (held-out
    motion), render, relight, export (USD, glTF), evaluate (synthetic captures); skips finished
    stages; writes OUT/report.md."""
    from ..pipeline import run as run_pipeline
    from ..report import write_report

    rec = run_pipeline(capture, out, config, say=lambda text: console.print(text, highlight=False))
    path = write_report(out)
    console.print(f"done in {rec['_total_seconds_this_run']:.0f} s; report: {path}")
